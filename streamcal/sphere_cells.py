"""The sphere of field directions: equal-area cells, the largest empty cap, and what to do
about it in words.

Cells: an equal-area zonal partition ("igloo"): the sphere is cut into an even number of bands of
latitude (so the equator is a band edge and a hemisphere fills exactly half of the cells), band
``k`` holds ``n_k`` cells of equal longitude width, ``n_k`` ∝ the band's circumference so cells are
roughly square, and the band edges in ``z`` are placed so that every cell has the same area
(a band's area is ``2π Δz``, Archimedes). Looking up a cell is one ``searchsorted`` and one
``floor``, O(1) per sample — a nearest-centre search over a Fibonacci set would cost O(cells).
HEALPix would do too but is not among our dependencies for this one small job.
"""
from __future__ import annotations

import numpy as np


class SphereCells:
    """Equal-area partition of the unit sphere into about ``n_cells`` cells."""

    def __init__(self, n_cells: int = 300):
        if n_cells < 2:
            raise ValueError(f"n_cells must be ≥ 2, got {n_cells}")
        side = np.sqrt(4.0 * np.pi / n_cells)                 # side of a square cell, rad
        n_bands = max(2, 2 * int(round(np.pi / side / 2.0)))   # even: the equator is an edge
        theta_mid = (np.arange(n_bands) + 0.5) * np.pi / n_bands
        counts = np.maximum(1, np.round(2.0 * np.pi * np.sin(theta_mid) / side)).astype(int)
        counts = np.maximum(counts, counts[::-1])              # symmetric about the equator
        self.counts = counts                                   # (B,) cells per band, north first
        self.n_cells = int(counts.sum())
        self.offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
        # Band k spans area ∝ counts[k]: z edges from +1 (north) down to −1.
        self.z_edges = 1.0 - 2.0 * np.concatenate([[0], np.cumsum(counts)]) / self.n_cells
        self.z_edges[-1] = -1.0
        band = np.repeat(np.arange(n_bands), counts)
        j = np.arange(self.n_cells) - self.offsets[band]
        z = 0.5 * (self.z_edges[band] + self.z_edges[band + 1])
        phi = -np.pi + (j + 0.5) * 2.0 * np.pi / counts[band]
        z = np.where(counts[band] == 1, np.sign(z), z)         # polar caps: centre on the pole
        rho = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
        #: (C,3) unit centre of each cell.
        self.centers = np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)

    def cell_of(self, d: np.ndarray) -> np.ndarray:
        """Cell index (n,) of unit directions ``d`` (n,3)."""
        # z_edges decrease; search on the negated, increasing edges.
        band = np.searchsorted(-self.z_edges[1:-1], -d[:, 2], side="right")
        phi = np.arctan2(d[:, 1], d[:, 0])
        n = self.counts[band]
        j = np.minimum((phi + np.pi) * (n / (2.0 * np.pi)), n - 1).astype(np.intp)
        return self.offsets[band] + j



def fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` nearly uniform unit vectors (n,3) on a Fibonacci spiral."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i
    rho = np.sqrt(1.0 - z * z)
    return np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)


def fibonacci_cap(n: int, cos_radius: float) -> np.ndarray:
    """``n`` nearly uniform unit vectors (n,3) over the cap ``z ≥ cos_radius``."""
    i = np.arange(n) + 0.5
    z = 1.0 - (1.0 - cos_radius) * i / n
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i
    rho = np.sqrt(1.0 - z * z)
    return np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)


def largest_empty_cap(d: np.ndarray, n_probe: int = 1000) -> tuple[np.ndarray, float]:
    """Centre (3,) and angular radius (degrees) of the largest spherical cap that contains none
    of the unit directions ``d`` (n,3): the probe point farthest from its nearest sample over a
    Fibonacci grid of ``n_probe`` points, then refined on a finer local grid around it."""
    if not len(d):
        return np.array([0.0, 0.0, -1.0]), 180.0
    probes = fibonacci_sphere(n_probe)
    best, cos_best = _farthest(probes, d)
    # Refine on a dense grid over a cap of two grid spacings around the best probe.
    spacing = np.sqrt(4.0 * np.pi / n_probe)
    local = fibonacci_cap(n_probe // 4, np.cos(2.0 * spacing)) @ _rotation_to(best).T
    best2, cos2 = _farthest(np.vstack([best[None, :], local]), d)
    return best2, float(np.degrees(np.arccos(np.clip(cos2, -1.0, 1.0))))


def _farthest(probes, d):
    nearest = np.empty(len(probes))
    # Chunks bound the memory and keep each product under OpenBLAS's threading threshold
    # (m·n·k ≤ 2¹⁸): its threads gain nothing with k = 3 and, spinning, made this 50× slower
    # on a busy 2-core machine.
    step = int(np.clip(2 ** 18 // (3 * max(len(d), 1)), 8, 512))
    for start in range(0, len(probes), step):
        nearest[start:start + step] = (probes[start:start + step] @ d.T).max(axis=1)
    k = int(np.argmin(nearest))
    return probes[k], nearest[k]


def _rotation_to(v):
    """Rotation matrix taking +z to the unit vector ``v``."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, v)
    s, c = np.linalg.norm(axis), float(v @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / s
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * Kx + (1 - c) * Kx @ Kx


_AXES = (("the nose (+X)", "the tail (−X)"), ("the left side (+Y)", "the right side (−Y)"),
         ("the top (+Z)", "the underside (−Z)"))


def describe_direction(v) -> str:
    """Body-axis words for a unit vector: its (at most two) largest axes with |component| ≥
    sin 22.5°."""
    v = np.asarray(v, dtype=float)
    order = np.argsort(-np.abs(v))
    parts = [_AXES[k][0 if v[k] > 0 else 1] for k in order[:2] if abs(v[k]) >= 0.38]
    return " and ".join(parts) if parts else _AXES[order[0]][0 if v[order[0]] > 0 else 1]


def hint(center, radius_deg: float, fraction: float) -> str:
    """What to do to fill the largest empty cap, in plain language."""
    if radius_deg < 20.0:
        return "coverage is good: no action needed"
    where = describe_direction(center)
    size = "half the sphere" if radius_deg >= 80 else f"a {radius_deg:.0f}° cap"
    return (f"field directions around {where} are missing ({size}): turn the board to point "
            f"{where} along the local field (north and down in the northern hemisphere, north "
            f"and up in the southern), then rotate it slowly about that direction")
