"""Small random scenes for the scene tests (tiny sizes: the whole suite shares 2 CPU cores)."""
from __future__ import annotations

import numpy as np

from fourlegs_engine.scene import Camera, CameraRig, GaussianSequence, Scene


def random_unit_quaternions(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    q = rng.normal(size=shape + (4,))
    return (q / np.linalg.norm(q, axis=-1, keepdims=True)).astype(np.float32)


def random_sequence(T: int = 3, N: int = 40, *, sh_degree: int | None = 1, colors: bool = False,
                    foreground: bool = True, per_frame_scales: bool = False, seed: int = 0) -> GaussianSequence:
    rng = np.random.default_rng(seed)
    f32 = lambda a: np.asarray(a, dtype=np.float32)  # noqa: E731
    return GaussianSequence(
        means=f32(rng.normal(size=(T, N, 3))),
        rotations=random_unit_quaternions(rng, (T, N)),
        log_scales=f32(rng.normal(-3, 0.5, size=(T, N, 3) if per_frame_scales else (N, 3))),
        opacity_logits=f32(rng.normal(size=N)),
        colors=f32(rng.random((T, N, 3))) if colors else None,
        sh=f32(rng.normal(size=(N, (sh_degree + 1) ** 2, 3))) if sh_degree is not None else None,
        foreground=(rng.random(N) > 0.5) if foreground else None,
    )


def dome_rig(T: int, num_train: int = 3, num_test: int = 1, width: int = 64, height: int = 48) -> CameraRig:
    def cam(i: int, n: int, name: str) -> Camera:
        a = 2 * np.pi * i / n
        return Camera.look_at((4 * np.cos(a), 4 * np.sin(a), 1.5), (0, 0, 0.5), width=width, height=height,
                              name=name)
    train = [cam(i, num_train, str(i + 1)) for i in range(num_train)]
    test = [cam(i + 0.5, num_test, str(100 + i)) for i in range(num_test)]
    return CameraRig.static(train, test, T)


def random_scene(T: int = 3, N: int = 40, **kw) -> Scene:
    g = random_sequence(T, N, **kw)
    return Scene(gaussians=g, cameras=dome_rig(T), name="random", fps=25.0)


def assert_sequences_equal(a: GaussianSequence, b: GaussianSequence, *, rot_atol: float = 0.0) -> None:
    np.testing.assert_array_equal(np.asarray(a.means), np.asarray(b.means))
    np.testing.assert_allclose(np.asarray(a.rotations), np.asarray(b.rotations), rtol=0, atol=rot_atol)
    np.testing.assert_array_equal(np.asarray(a.log_scales), np.asarray(b.log_scales))
    np.testing.assert_array_equal(np.asarray(a.opacity_logits), np.asarray(b.opacity_logits))
    for name in ("colors", "sh", "foreground", "labels"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=name)


def assert_rigs_equal(a: CameraRig, b: CameraRig) -> None:
    assert a.num_timesteps == b.num_timesteps
    for split in ("train", "test"):
        for t in range(a.num_timesteps):
            ca, cb = a.cameras(t, split), b.cameras(t, split)
            assert [c.name for c in ca] == [c.name for c in cb]
            for x, y in zip(ca, cb):
                np.testing.assert_array_equal(x.K, y.K)
                np.testing.assert_array_equal(x.w2c, y.w2c)
                assert (x.width, x.height) == (y.width, y.height)
