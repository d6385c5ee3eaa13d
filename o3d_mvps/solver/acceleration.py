"""Anderson acceleration across a level's sweeps (type II, small memory).

A sweep maps the unknowns x (depth, albedo, lights, poses, LED offset) to g = G(x). Alternating
sweeps creep along the valley where these trade off; Anderson's point combines the last few
sweeps' outputs so that the combination of their updates f = g - x is smallest:

    gamma = argmin || f_k - sum_i gamma_i (f_{i+1} - f_i) ||,
    x_A = g_k - sum_i gamma_i (g_{i+1} - g_i),

over the last ``memory`` differences. The least squares fits the lights and the LED offset only
(:data:`ANDERSON_FITTED`, each block scaled by its latest update's norm): they follow the slow
mode, where the depth's and albedo's updates are dominated by pixel-level noise. Every unknown is
mixed with the same gamma; the poses as twists (se(3)) relative to the latest sweep's. The point
is a proposal only: the driver keeps it, or half the way to it, where that lowers the energy
(:func:`.driver._accelerated`), else extrapolates as before. Works on the host (NumPy) and on a
GPU (the depth and albedo in the array module of ``est.z``, the small blocks on the host).
"""

from __future__ import annotations

import numpy as np

from ..model import se3
from .problem import Estimate

#: sweeps remembered (differences of consecutive sweeps); 0 turns the acceleration off
ANDERSON_MEMORY = 3
#: the blocks whose updates the least squares fits (all blocks are mixed with its coefficients).
#: D415 render's finest level: the lights move along the valley sweep after sweep (consecutive
#: updates at cosine 1.00, each 0.76-0.91 times the last: a slow linear mode), the depth's and
#: albedo's updates carry pixel-level noise (cosine -0.4 to 0.8) and the poses' 0.2-1.0;
#: fitting every block (each scaled to norm 1) let that noise keep gamma near 0, and the
#: accelerated solve was no faster (39 -> 41 sweeps)
ANDERSON_FITTED = ("lights", "led_offset")
#: fractions of the way from the sweep's result to Anderson's point that the driver tries, in order
ANDERSON_FRACTIONS = (1.0, 0.5)
#: light models whose levels are not accelerated. Point lights (static captures): on the
#: D415-like quilt (benchmarks.static, --no-sh) the albedo error fell (320x240: 0.944 -> 0.906 %,
#: clean render 0.335 -> 0.282 %; 640x480: 0.663 -> 0.660, clean 0.171 -> 0.109 %) and the CPU
#: with it (320x240: 6.05 -> 5.23 s), but the noisy render's lamps ended further off (320x240:
#: 9.6 -> 11.7 mm, tests/test_static_camera.py's bound 12; 640x480: 5.2 -> 6.8 mm) while the clean
#: render's came closer (13.1 -> 9.9 mm; 6.0 -> 0.9 mm): left as before until the lamps are understood
NOT_ACCELERATED = ("point",)
#: the remembered differences of the depth and albedo (the bulk of the history: at 2 MP, 948k
#: pixels, 3 x 4 values a pixel, 45 MB, besides the last sweep's output, 30 MB in float64)
HISTORY_DTYPE = np.float32
#: Tikhonov regularisation of the small least squares, relative to its Gram matrix's trace
ANDERSON_REGULARISATION = 1e-8


#: object pixels above which a level is not accelerated. Its points were refused on every large
#: level measured: the 2 MP render's levels of 240k and 958k pixels (0 of 3 and 0 of 5 proposals
#: kept; 60k: 0 of 4). A refused point leaves the sweep as it was, so such a level gives the same
#: result without it, less the refusals' two energy evaluations each (2 MP: 11 CPU s) and the
#: history (90 MB at 2 MP, where it took the peak from 3003 to 3091 MiB, past 3 GiB). The D415
#: render's finest level (89 619 pixels) kept 1 of 5, and that one point left the result worse:
#: without it 1.29228 deg / 0.51822 mm against 1.29601 / 0.51865, in the same 6 sweeps, and 0.26
#: main-thread s less (150 000 before). Its coarser levels (22 284 pixels and fewer) keep nearly
#: all, as does the demo's finest level (640x480, about 22 000)
ANDERSON_MAX_PIXELS = 50_000


def level_accelerator(light_name: str, pixels: int) -> Anderson | None:
    """A level's :class:`Anderson` history (:data:`ANDERSON_MEMORY`, read when called), or None
    where the acceleration is off (memory 0), the light model is in :data:`NOT_ACCELERATED` or
    the level has more than :data:`ANDERSON_MAX_PIXELS` object pixels ``pixels``."""
    if ANDERSON_MEMORY <= 0 or light_name in NOT_ACCELERATED or pixels > ANDERSON_MAX_PIXELS:
        return None
    return Anderson(ANDERSON_MEMORY)


class Anderson:
    """Anderson type-II mixing over sweeps of one level (history kept between calls).

    Parameters
    ----------
    memory : int
        How many differences of consecutive sweeps the least squares uses (at most).
    """

    def __init__(self, memory: int):
        self.memory = int(memory)
        self.proposed = self.kept = 0  # points proposed, and kept by the caller (its count)
        self.restart()

    def restart(self) -> None:
        """Forget the history (the next sweep starts a new one)."""
        self._f = None  # the last sweep's update f = g - x of the fitted blocks ({name: array})
        self._g = None  # the last sweep's output g, every block (poses: the (n, 4, 4) themselves)
        self._df, self._dg = [], []  # differences of consecutive f and g, oldest first

    def propose(self, est: Estimate, before: Estimate) -> Estimate | None:
        """Record the sweep ``before`` -> ``est`` (its start and its output) and return Anderson's
        point (a new :class:`Estimate`, depth not clipped), or None while there is no history or
        the least squares is degenerate. ``est`` and ``before`` are not modified."""
        f = {name: getattr(est, name) - getattr(before, name) for name in ANDERSON_FITTED
             if getattr(est, name) is not None and getattr(before, name) is not None}
        g = tuple(None if x is None else x.copy() for x in (est.z, est.albedo, est.lights, est.poses, est.led_offset))
        if self._g is not None and _same_shapes(self._g, g) and f.keys() == self._f.keys():
            self._df.append({name: f[name] - self._f[name] for name in f})
            self._dg.append(_difference(g, self._g))
            del self._df[:-self.memory], self._dg[:-self.memory]
        else:
            self._df, self._dg = [], []
        self._f, self._g = f, g
        if not self._df:
            return None
        gamma = self._coefficients(f)
        if gamma is None:
            return None
        self.proposed += 1
        return _combined(est, self._dg, gamma)

    def _coefficients(self, f: dict) -> np.ndarray | None:
        """gamma (m,) of the least squares in the module docstring (each block of ``f`` scaled to
        norm 1), or None where it is degenerate."""
        m = len(self._df)
        gram, rhs = np.zeros((m, m)), np.zeros(m)
        for name, fb in f.items():
            norm2 = float(np.vdot(fb, fb))
            if not norm2 > 0:
                continue
            cols = [np.ravel(df[name]) for df in self._df]
            for i in range(m):
                rhs[i] += float(np.vdot(cols[i], fb)) / norm2
                for j in range(i, m):
                    gram[i, j] += float(np.vdot(cols[i], cols[j])) / norm2
        gram = np.triu(gram) + np.triu(gram, 1).T
        trace = np.trace(gram)
        if not (np.isfinite(trace) and trace > 0):
            return None
        gamma = np.linalg.solve(gram + ANDERSON_REGULARISATION * trace * np.eye(m), rhs)
        return gamma if np.all(np.isfinite(gamma)) else None


def partway(est: Estimate, point: Estimate, fraction: float) -> Estimate:
    """``est + fraction (point - est)`` by block (the poses along their twists)."""
    if fraction == 1.0:
        return Estimate(point.z, point.albedo, point.lights, point.poses, point.led_offset)
    poses = np.stack([se3.exp(fraction * se3.log(T @ np.linalg.inv(T0))) @ T0 for T, T0 in zip(point.poses, est.poses)])
    offset = None if est.led_offset is None else est.led_offset + fraction * (point.led_offset - est.led_offset)
    return Estimate(est.z + fraction * (point.z - est.z), est.albedo + fraction * (point.albedo - est.albedo),
                    est.lights + fraction * (point.lights - est.lights), poses, offset)


def _difference(g: tuple, g0: tuple) -> tuple:
    """g - g0 by block, the depth's and albedo's in :data:`HISTORY_DTYPE`, the poses as twists
    (n, 6) (``exp(twist) @ g0 = g``)."""
    z, albedo, lights, poses, offset = g
    z0, albedo0, lights0, poses0, offset0 = g0
    return ((z - z0).astype(HISTORY_DTYPE), (albedo - albedo0).astype(HISTORY_DTYPE), lights - lights0,
            np.stack([se3.log(T @ np.linalg.inv(T0)) for T, T0 in zip(poses, poses0)]),
            None if offset is None or offset0 is None else offset - offset0)


def _same_shapes(a: tuple, b: tuple) -> bool:
    return all((x is None) == (y is None) and (x is None or x.shape == y.shape) for x, y in zip(a, b))


def _combined(est: Estimate, dg: list, gamma: np.ndarray) -> Estimate:
    """g_k - sum_i gamma_i dg_i, by block (the poses: exp(-sum_i gamma_i twist_i) @ T)."""
    def mix(b, x):
        if x is None:
            return None
        out = x
        for gi, d in zip(gamma, dg):
            if d[b] is not None:
                out = out - float(gi) * d[b]
        return out

    twist = mix(3, np.zeros((len(est.poses), 6)))
    poses = np.stack([se3.exp(w) @ T for w, T in zip(twist, est.poses)])
    return Estimate(mix(0, est.z), mix(1, est.albedo), mix(2, est.lights), poses, mix(4, est.led_offset))
