"""The camera's code pass drawn single-sampled (sensors.camera._single_sample) gives the codes of
pyrender's own multisample-and-resolve path exactly, and its depth to the depth buffer's rounding."""

import subprocess
import sys
from pathlib import Path

import numpy as np

from sensors.camera import linear_depth

ROOT = Path(__file__).resolve().parents[2]

# Renders one city frame's right camera in a fresh process (each process gets its own EGL context);
# "pyrender" leaves pyrender's 4-sample framebuffer and resolve blits in place.
_SCRIPT = """
import sys
import numpy as np
import sensors.camera as C
if sys.argv[1] == "pyrender":
    C._single_sample = lambda renderer: None
from tests.sensors.conftest import render
scenes, renderer = render("city", seed=1)
scene = scenes[0]
renderer._set_actors(scene)
cam = renderer.calib.camera("camera_right")
index, material, depth = renderer.stereo.codes(cam, scene.ego.pose)
inner = C._RENDERERS[(cam.width, cam.height)]._renderer
np.savez(sys.argv[2], index=index, material=material, depth=depth,
         shared=np.array(inner._main_fb_ms == inner._main_fb))
"""


def _codes(tmp_path, how):
    out = tmp_path / f"{how}.npz"
    subprocess.run([sys.executable, "-c", _SCRIPT, how, str(out)], cwd=ROOT, check=True, timeout=300)
    return np.load(out)


def test_single_sample_pass_equals_pyrenders_resolved_pass(tmp_path):
    ours, theirs = _codes(tmp_path, "ours"), _codes(tmp_path, "pyrender")
    assert bool(ours["shared"]) and not bool(theirs["shared"])  # each ran the path it names
    np.testing.assert_array_equal(ours["index"], theirs["index"])
    np.testing.assert_array_equal(ours["material"], theirs["material"])
    a, b = ours["depth"], theirs["depth"]
    np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b))
    finite = np.isfinite(a)
    assert finite.mean() > 0.3 and (ours["index"] > 0).any()
    # a 24-bit depth buffer rounds z_ndc to 2^-24: the relative step at depth z is ~ z / (near 2^23)
    rel = np.abs(a[finite] - b[finite]) / b[finite]
    assert rel.max() < 2e-4, rel.max()


def test_linear_depth_inverts_the_perspective_depth_buffer():
    near, far = 0.1, 500.0
    z = np.array([0.1, 0.5, 2.0, 10.0, 80.0, 499.0])
    # OpenGL: z_ndc = (f + n - 2 f n / z) / (f - n), buffer = (z_ndc + 1) / 2
    buffer = (((far + near) - 2 * far * near / z) / (far - near) + 1) / 2
    got = linear_depth(np.append(buffer, 1.0).astype(np.float32).reshape(1, -1), near, far)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got[0, :-1], z, rtol=5e-3)
    assert got[0, -1] == 0.0  # nothing drawn
    # same float32 arithmetic as pyrender's Renderer._read_main_framebuffer
    d = np.float32(buffer[3])
    zn = np.float32(2.0) * d - np.float32(1.0)
    assert got[0, 3] == np.float32((2.0 * near * far) / (np.float32(far + near) - zn * np.float32(far - near)))


def test_linear_depth_equals_pyrenders_numpy():
    def pyrenders(buffer, znear, zfar):  # pyrender's Renderer._read_main_framebuffer (and linear_depth up to now)
        background = buffer == 1.0
        out = 2.0 * buffer - 1.0
        drawn = ~background
        out[drawn] = (2.0 * znear * zfar) / (zfar + znear - out[drawn] * (zfar - znear))
        out[background] = 0.0
        return out

    rng = np.random.default_rng(0)
    buffer = rng.random((50, 60)).astype(np.float32)
    buffer[rng.random((50, 60)) < 0.2] = 1.0
    buffer[0, :4] = [0.0, np.nextafter(np.float32(1), np.float32(0)), 0.5, 1e-30]
    for near, far in ((0.3, 400.0), (0.1, 500.0)):
        for b in (buffer, buffer[::-1]):  # the camera passes the flipped read-back
            ref = pyrenders(b.copy(), near, far)
            got = linear_depth(b, near, far)
            assert got.dtype == ref.dtype and got.tobytes() == ref.tobytes()
