"""Run in a fresh process by tests/bake/test_bake_warm_up.py: open a .blend, prepare the solver
for it (addon.bake.warm_up.prepare_for), then bake it, and print as JSON the kernel signatures
the bake added after the preparation (each one a compile with a cold Numba cache).

    python tests/bake/_prepare_check.py SCENE.blend RESOLUTION [ESTIMATOR]
"""

import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from numba.core.dispatcher import Dispatcher  # noqa: E402

from addon.bake.extract import extract_scene, open_blend  # noqa: E402
from addon.bake.pipeline import BakeSettings, bake  # noqa: E402
from addon.bake.warm_up import prepare_for  # noqa: E402


def signatures():
    out = {}
    for name, mod in list(sys.modules.items()):
        if name.startswith("addon") and mod is not None:
            for v in list(vars(mod).values()):
                v = getattr(v, "chunk_kernel", v)  # a runtime.jit.parallel_range function: its kernel
                if isinstance(v, Dispatcher):
                    out[f"{v.py_func.__module__}.{v.py_func.__qualname__}"] = {str(s) for s in v.signatures}
    return out


blend, res = sys.argv[1], int(sys.argv[2])
settings = BakeSettings(resolution=res, samples=4, estimator=sys.argv[3] if len(sys.argv) > 3 else "forward-flux")
open_blend(blend)
scene = extract_scene(resolution=res)
seconds, chains = prepare_for(scene, settings)
before = signatures()
result = bake(scene, settings)
after = signatures()
new = {k: sorted(v - before.get(k, set())) for k, v in after.items() if v - before.get(k, set())}
print(json.dumps({"chains": list(chains), "baked": result.report["plan"]["summary"], "prepared": len(before),
                  "new": new, "seconds": seconds}))
