"""The eel FOM's geometry on its grid: regions, chamber walls, pressure loads, centerline.

Pure functions of the configuration and the mesh that :class:`~soft_rom.sim.eel.EelModel`
builds its operators from: which grid cells are couplers and chambers
(:func:`chamber_cells`), the chambers' wall triangles (:func:`wall_triangles`), the force per
unit pressure on them (:func:`triangle_forces`, :func:`pressure_matrix`) and the sparse map
from nodal positions to the centerline points (:func:`centerline_map`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
import scipy.sparse as sp

from soft_rom.errors import ConfigError
from soft_rom.sim.eel_types import EelConfig
from soft_rom.sim.mesh import cavity_faces, TetMesh

__all__ = ['centerline_map', 'chamber_cells', 'pressure_matrix', 'triangle_forces',
           'wall_triangles']

Array = NDArray[np.float64]


def chamber_cells(cfg: EelConfig, xs: Array, ys: Array, zs: Array
                  ) -> tuple[NDArray[np.int64], list[NDArray[np.bool_]]]:
    """Region of every grid cell (0 soft, 1 coupler, -1 cavity) and each chamber's cells.

    Returns
    -------
    region : ndarray of int, shape (nx, ny, nz)
    chambers : list of ndarray of bool, shape (nx, ny, nz)
        Per segment, the top chamber (``z > 0``) then the bottom one.
    """
    nx, ny, nz = len(xs) - 1, len(ys) - 1, len(zs) - 1
    xc, yc, zc = (0.5 * (a[1:] + a[:-1]) for a in (xs, ys, zs))
    X, Y, Z = np.meshgrid(xc, yc, zc, indexing='ij')
    region = np.zeros((nx, ny, nz), dtype=np.int64)
    for a, b in cfg.couplers:
        region[(X > a) & (X < b)] = 1
    chambers = []
    for a, b in cfg.segments:
        in_x = (X > a + cfg.chamber_margin) & (X < b - cfg.chamber_margin)
        in_y = np.abs(Y) < cfg.chamber_y
        for sign in (1, -1):
            in_z = (sign * Z > cfg.chamber_z[0]) & (sign * Z < cfg.chamber_z[1])
            cav = in_x & in_y & in_z
            if not cav.any():
                raise ConfigError('a chamber has no cell at this resolution; refine the mesh '
                                  'or enlarge the chambers.')
            chambers.append(cav)
            region[cav] = -1
    return region, chambers


def wall_triangles(xs: Array, ys: Array, zs: Array, region: NDArray[np.int64],
                   chambers: list[NDArray[np.bool_]], mesh: TetMesh, fiber_reinforced: bool
                   ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The loaded wall triangles ``(n_tri, 3)`` of all chambers and the chamber of each.

    Fiber-reinforced chambers are loaded on their end caps only (walls normal to ``x``).
    """
    tris, owner = [], []
    for c, cav in enumerate(chambers):
        tri = cavity_faces(xs, ys, zs, region, cav, mesh,
                           axes=(0,) if fiber_reinforced else (0, 1, 2))
        tris.append(tri)
        owner.append(np.full(len(tri), c))
    return np.concatenate(tris), np.concatenate(owner)


def triangle_forces(triangles: NDArray[np.int64], x: Array) -> Array:
    """Force per unit pressure on each corner of each wall triangle, shape (n_tri, 3)."""
    t = triangles
    return np.cross(x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]]) / 6.0


def pressure_matrix(triangles: NDArray[np.int64], chamber: NDArray[np.int64], nodes: Array,
                    n_chambers: int) -> sp.csr_matrix:
    """``B``, shape (3 n_nodes, n_chambers): nodal force per unit pressure at rest."""
    f_rest = triangle_forces(triangles, nodes)                 # (n_tri, 3) per unit p
    dof = 3 * triangles[:, :, None] + np.arange(3)             # (n_tri, 3, 3)
    B = sp.csr_matrix(
        (np.broadcast_to(f_rest[:, None, :], dof.shape).ravel(),
         (dof.ravel(), np.repeat(chamber, 9))),
        shape=(3 * len(nodes), n_chambers))
    B.sum_duplicates()
    return B


def centerline_map(mesh: TetMesh, xs: Array, length: float, n_centerline: int
                   ) -> sp.csr_matrix:
    """Centerline points = ``map @ positions``, shape (n_centerline, n_nodes).

    Each point is the mean of the nodes of the nearest grid cross-sections, linearly
    interpolated along ``x``; the points are evenly spaced from ``x = 0`` to ``length``.
    """
    gi = mesh.grid_index[:, 0]
    counts = np.bincount(gi, minlength=len(xs))
    stations = np.linspace(0.0, length, n_centerline)
    dx = xs[1] - xs[0]
    rows, cols, vals = [], [], []
    for s, xq in enumerate(stations):
        f = min(xq / dx, len(xs) - 1 - 1e-12)
        i0 = int(np.floor(f))
        w1 = f - i0
        for i, w in ((i0, 1 - w1), (i0 + 1, w1)):
            if w <= 1e-14:
                continue
            nodes = np.nonzero(gi == i)[0]
            rows.append(np.full(nodes.size, s))
            cols.append(nodes)
            vals.append(np.full(nodes.size, w / counts[i]))
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                 np.concatenate(cols))),
                         shape=(n_centerline, mesh.n_nodes))
