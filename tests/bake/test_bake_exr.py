"""EXR output (addon/bake/exr.py): float32 RGB, first scanline = top of the texture (v = 1)."""

import numpy as np
import OpenEXR

from addon.bake.exr import read_exr, write_exr


def test_first_scanline_is_the_top_row_and_values_round_trip(tmp_path):
    H, W = 5, 7
    img = np.zeros((H, W, 3), np.float32)
    img[0] = (1.0, 2.0, 3.0)  # row 0 = bottom (v = 0), as Blender stores pixels
    img[H - 1] = (7.0, 8.0, 9.0)  # top (v = 1)
    img[2, 3] = (1e-7, 12345.678, 0.5)
    path = tmp_path / "t.exr"
    write_exr(path, img)
    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = f.channels()
        assert set(ch) == {"R", "G", "B"}
        r = ch["R"].pixels
        assert r.dtype == np.float32 and r.shape == (H, W)
        assert np.all(r[0] == 7.0) and np.all(r[-1] == 1.0)  # file top = texture top
        assert ch["G"].pixels[H - 1 - 2, 3] == np.float32(12345.678)
    np.testing.assert_array_equal(read_exr(path), img)


def test_grey_input_becomes_rgb(tmp_path):
    grey = np.arange(6, dtype=np.float64).reshape(2, 3)
    write_exr(tmp_path / "g.exr", grey)
    out = read_exr(tmp_path / "g.exr")
    assert out.shape == (2, 3, 3) and np.array_equal(out[:, :, 1], grey.astype(np.float32))
