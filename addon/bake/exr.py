"""Float32 RGB EXR files with the OpenEXR Python bindings (no bpy).

Images in the bake are (H, W, 3) arrays whose row 0 is the bottom of the texture (v = 0, as
Blender stores pixels).  EXR scanlines go top to bottom, so the first scanline written is
row H - 1 (v = 1): the file looks as the texture does in Blender's image editor.
"""

import numpy as np


def write_exr(path, image, compression="ZIP"):
    """Write (H, W, 3) (or (H, W)) irradiance, row 0 = bottom, as float32 RGB (ZIP compressed)."""
    import OpenEXR

    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) image, got {img.shape}")
    top_first = np.ascontiguousarray(img[::-1])
    comp = getattr(OpenEXR, f"{compression}_COMPRESSION")
    header = {"compression": comp, "type": OpenEXR.scanlineimage}
    channels = {"R": np.ascontiguousarray(top_first[:, :, 0]), "G": np.ascontiguousarray(top_first[:, :, 1]),
                "B": np.ascontiguousarray(top_first[:, :, 2])}
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))


def read_exr(path):
    """Read an RGB EXR into (H, W, 3) float32 with row 0 = bottom (the inverse of :func:`write_exr`)."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = f.channels()
        rgb = [np.asarray(ch[c].pixels, dtype=np.float32) for c in ("R", "G", "B")]
    return np.ascontiguousarray(np.stack(rgb, axis=2)[::-1])
