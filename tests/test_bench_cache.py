"""bench/run.py's conversion of renders cached before the standard lat-long files: every envmap the capture's
truth.json lists is rewritten in the standard layout (read back by objcam.envmap.read_latlong as the old file read
raw), the old folder is left as it was, and nothing else changes."""

import json

import numpy as np

from bench.run import convert_old_render
from objcam.envmap import read_latlong
from objcam.image_io import read_exr, write_exr


def test_old_render_truths_are_permuted_once_and_the_source_is_kept(tmp_path):
    old, new = tmp_path / "render", tmp_path / "render-std"
    rng = np.random.default_rng(0)
    maps = {"a": rng.random((4, 8, 3)).astype(np.float32), "b": rng.random((4, 8, 3)).astype(np.float32)}
    for k, m in maps.items():
        (old / "truth" / k).mkdir(parents=True)
        write_exr(old / "truth" / k / "envmap.exr", m)  # objcam's own grid, as renders before issue 23 wrote it
    clean = rng.random((6, 6, 3)).astype(np.float32)
    write_exr(old / "truth" / "a" / "clean.exr", clean)
    (old / "truth" / "truth.json").write_text(json.dumps({"envmaps": {k: f"truth/{k}/envmap.exr" for k in maps}}))
    (old / "capture.toml").write_text("")
    convert_old_render(old, new)
    for k, m in maps.items():
        np.testing.assert_array_equal(read_latlong(new / "truth" / k / "envmap.exr"), m)
        np.testing.assert_array_equal(read_exr(old / "truth" / k / "envmap.exr"), m)  # the source untouched
        assert not np.array_equal(read_exr(new / "truth" / k / "envmap.exr"), m)  # the file itself was permuted
    np.testing.assert_array_equal(read_exr(new / "truth" / "a" / "clean.exr"), clean)  # not a lat-long map
    assert (new / "capture.toml").is_file() and not (tmp_path / "render-std.tmp").exists()
