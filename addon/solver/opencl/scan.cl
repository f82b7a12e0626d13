// Exclusive prefix sums of int arrays on the device, for compactions whose output order must not
// depend on the order work-items finish in (the one-bounce survivors and path records): a
// position is the number of earlier elements, so the compacted order is the input order.
//
// Three kernels over n elements in work-groups of L:
//   scan_blocks: each group's elements are scanned in local memory (Hillis-Steele); out[i] is the
//                sum of the group's elements before i, sums[g] the group's total;
//   scan_sums:   one work-group scans sums[0 .. n_blocks) in place (each work-item a run of
//                consecutive blocks) and writes the grand total to sums[n_blocks];
//   scan_add:    out[i] += sums[group of i].
// Integer sums are exact, so the result does not depend on L or on the device.

// tmp[lid] = the sum of the values of work-items 0..lid of the group (Hillis-Steele in local
// memory; every work-item of the group must call it).
static void work_group_inclusive_scan(__local int *tmp, int value) {
    int lid = get_local_id(0), L = get_local_size(0);
    tmp[lid] = value;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int off = 1; off < L; off <<= 1) {
        int add = lid >= off ? tmp[lid - off] : 0;
        barrier(CLK_LOCAL_MEM_FENCE);
        tmp[lid] += add;
        barrier(CLK_LOCAL_MEM_FENCE);
    }
}

__kernel void scan_blocks(__global const int *in, __global int *out, __global int *sums, const int n,
                          __local int *tmp) {
    int i = get_global_id(0), lid = get_local_id(0), L = get_local_size(0);
    int v = i < n ? in[i] : 0;
    work_group_inclusive_scan(tmp, v);
    if (i < n) out[i] = tmp[lid] - v;
    if (lid == L - 1) sums[get_group_id(0)] = tmp[lid];
}

__kernel void scan_sums(__global int *sums, const int n_blocks, __local int *tmp) {
    int lid = get_local_id(0), L = get_local_size(0);
    int per = (n_blocks + L - 1) / L, lo = min(lid * per, n_blocks), hi = min(lo + per, n_blocks);
    int run = 0;
    for (int b = lo; b < hi; ++b) run += sums[b];
    work_group_inclusive_scan(tmp, run);
    int acc = tmp[lid] - run;
    for (int b = lo; b < hi; ++b) { int s = sums[b]; sums[b] = acc; acc += s; }
    if (lid == L - 1) sums[n_blocks] = tmp[lid];
}

__kernel void scan_add(__global int *out, __global const int *sums, const int n) {
    int i = get_global_id(0);
    if (i < n) out[i] += sums[get_group_id(0)];
}
