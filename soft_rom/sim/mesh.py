"""Structured tetrahedral meshes of boxes with void cells (fluid chambers).

A box ``[0, Lx] x [-Ly/2, Ly/2] x [-Lz/2, Lz/2]`` is cut into ``nx * ny * nz`` hexahedral
cells; every cell is split into six tetrahedra along its main diagonal (Kuhn/Freudenthal
split). All cells use the same split, so neighbouring cells share conforming faces, and the
mesh has no slivers. Cells can be removed (chamber cavities) and tagged with a material
region. Nodes are numbered x-major (``x`` slowest), so that the stiffness matrix of a long
body has a small bandwidth and sparse factorizations stay cheap.

A structured generator is used instead of gmsh because it is deterministic, fast (the
231,336-DOF mesh is built in seconds), needs no external binary and gives the chamber
walls exactly, which makes the pressure load map exact (see :func:`cavity_faces`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from soft_rom.errors import ConfigError

__all__ = ['NodalDOFs', 'TetMesh', 'box_grid', 'cavity_faces', 'tetrahedralize']

# The six tetrahedra of the unit cube (Kuhn split): corner c = (i, j, k) has index
# 4 i + 2 j + k; every tet follows one monotone path 000 -> 111 along the axes.
_KUHN = np.array([
    [0, 4, 6, 7],  # x, y, z
    [0, 4, 5, 7],  # x, z, y
    [0, 2, 6, 7],  # y, x, z
    [0, 2, 3, 7],  # y, z, x
    [0, 1, 5, 7],  # z, x, y
    [0, 1, 3, 7],  # z, y, x
], dtype=np.int64)


class NodalDOFs:
    """``n_nodes`` and ``n_dof`` of a body with nodal positions ``nodes`` (n_nodes, 3)."""

    nodes: NDArray[np.float64]

    @property
    def n_nodes(self) -> int:
        """Number of nodes."""
        return int(self.nodes.shape[0])

    @property
    def n_dof(self) -> int:
        """Number of degrees of freedom, ``3 * n_nodes`` (node-major: x0, y0, z0, x1, ...)."""
        return 3 * self.n_nodes


@dataclass(frozen=True)
class TetMesh(NodalDOFs):
    """A linear tetrahedral mesh.

    Parameters
    ----------
    nodes : ndarray, shape (n_nodes, 3)
        Rest positions in metres.
    tets : ndarray of int, shape (n_tets, 4)
        Node indices of each tetrahedron, positively oriented (positive volume).
    region : ndarray of int, shape (n_tets,)
        Material region of each tetrahedron (index into a material table).
    grid_index : ndarray of int, shape (n_nodes, 3)
        Structured ``(i, j, k)`` grid index of every node (for cross-section look-ups).
    spacing : tuple of float
        Cell size ``(dx, dy, dz)``.
    """

    nodes: NDArray[np.float64]
    tets: NDArray[np.int64]
    region: NDArray[np.int64]
    grid_index: NDArray[np.int64]
    spacing: tuple[float, float, float]
    info: dict = field(default_factory=dict)


def box_grid(length: float, width: float, height: float, nx: int, ny: int,
             nz: int) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Node coordinates along each axis of the box grid.

    Returns
    -------
    xs : ndarray, shape (nx + 1,)
        From 0 to ``length``.
    ys : ndarray, shape (ny + 1,)
        From ``-width / 2`` to ``width / 2``.
    zs : ndarray, shape (nz + 1,)
        From ``-height / 2`` to ``height / 2``.
    """
    for name, val in (('nx', nx), ('ny', ny), ('nz', nz)):
        if int(val) != val or val < 1:
            raise ConfigError(f'{name} must be a positive integer; got {val!r}.')
    xs = np.linspace(0.0, length, nx + 1)
    ys = np.linspace(-width / 2, width / 2, ny + 1)
    zs = np.linspace(-height / 2, height / 2, nz + 1)
    return xs, ys, zs


def tetrahedralize(xs: NDArray[np.float64], ys: NDArray[np.float64], zs: NDArray[np.float64],
                   cell_region: NDArray[np.int64]) -> TetMesh:
    """Split the solid cells of a structured grid into tetrahedra.

    Parameters
    ----------
    xs, ys, zs : ndarray
        Grid node coordinates along each axis, increasing.
    cell_region : ndarray of int, shape (nx, ny, nz)
        Material region of each cell; ``-1`` marks a void cell (no tetrahedra).

    Returns
    -------
    TetMesh
        Nodes not used by any tetrahedron (inside cavities) are dropped; the remaining ones
        keep their x-major order.
    """
    nx, ny, nz = len(xs) - 1, len(ys) - 1, len(zs) - 1
    cell_region = np.asarray(cell_region, dtype=np.int64)
    if cell_region.shape != (nx, ny, nz):
        raise ConfigError(f'cell_region must have shape {(nx, ny, nz)}; got {cell_region.shape}.')
    ci, cj, ck = np.nonzero(cell_region >= 0)
    if ci.size == 0:
        raise ConfigError('the grid has no solid cell.')

    def gid(i: NDArray, j: NDArray, k: NDArray) -> NDArray:
        return (i * (ny + 1) + j) * (nz + 1) + k

    corners = np.stack([gid(ci + a, cj + b, ck + c)
                        for a in (0, 1) for b in (0, 1) for c in (0, 1)], axis=1)
    tets = corners[:, _KUHN].reshape(-1, 4)
    region = np.repeat(cell_region[ci, cj, ck], 6)

    used = np.zeros((nx + 1) * (ny + 1) * (nz + 1), dtype=bool)
    used[tets.ravel()] = True
    new_index = np.cumsum(used) - 1
    old = np.nonzero(used)[0]
    gi, rem = np.divmod(old, (ny + 1) * (nz + 1))
    gj, gk = np.divmod(rem, nz + 1)
    nodes = np.stack([xs[gi], ys[gj], zs[gk]], axis=1)
    tets = new_index[tets]

    # orient every tet positively
    d = nodes[tets[:, 1:]] - nodes[tets[:, :1]]
    vol = np.einsum('ei,ei->e', d[:, 0], np.cross(d[:, 1], d[:, 2]))
    neg = vol < 0
    tets[neg, 2], tets[neg, 3] = tets[neg, 3].copy(), tets[neg, 2].copy()
    spacing = (float(xs[1] - xs[0]), float(ys[1] - ys[0]), float(zs[1] - zs[0]))
    return TetMesh(nodes=nodes, tets=tets, region=region,
                   grid_index=np.stack([gi, gj, gk], axis=1), spacing=spacing,
                   info={'grid': [nx, ny, nz]})


def cavity_faces(xs: NDArray[np.float64], ys: NDArray[np.float64], zs: NDArray[np.float64],
                 cell_region: NDArray[np.int64], cavity: NDArray[np.bool_],
                 mesh: TetMesh, *, axes: tuple[int, ...] = (0, 1, 2)) -> NDArray[np.int64]:
    """Wall triangles of a cavity of void cells, oriented from the cavity into the solid.

    Every face shared by a cavity cell and a solid cell is a wall; it is returned as the two
    triangles of the tetrahedra faces on it (the Kuhn split cuts each quad along the diagonal
    from its low to its high corner). A pressure ``p`` in the cavity acts on a triangle of
    area vector ``a = (x1 - x0) x (x2 - x0) / 2`` with force ``p a``, one third to each
    corner. For a closed cavity (all ``axes``) the forces cancel in every configuration.

    Parameters
    ----------
    cavity : ndarray of bool, shape (nx, ny, nz)
        Cells of this cavity (must be void in ``cell_region``).
    axes : tuple of int
        Keep only the walls normal to these axes (``(0,)``: the end caps).

    Returns
    -------
    ndarray of int, shape (n_tri, 3)
        Mesh node indices; ``(x1 - x0) x (x2 - x0)`` points out of the cavity.
    """
    nx, ny, nz = len(xs) - 1, len(ys) - 1, len(zs) - 1
    grid_to_mesh = -np.ones((nx + 1) * (ny + 1) * (nz + 1), dtype=np.int64)
    gi, gj, gk = mesh.grid_index.T
    grid_to_mesh[(gi * (ny + 1) + gj) * (nz + 1) + gk] = np.arange(mesh.n_nodes)
    tris = []
    ci, cj, ck = np.nonzero(cavity)
    for axis in axes:
        others = [a for a in range(3) if a != axis]
        for sign in (-1, 1):
            off = np.zeros(3, dtype=np.int64)
            off[axis] = sign
            ni, nj, nk = ci + off[0], cj + off[1], ck + off[2]
            inside = (ni >= 0) & (ni < nx) & (nj >= 0) & (nj < ny) & (nk >= 0) & (nk < nz)
            if not np.all(inside):
                raise ConfigError('a chamber cavity touches the outer surface of the body.')
            wall = cell_region[ni, nj, nk] >= 0
            lo = np.stack([ci[wall], cj[wall], ck[wall]], axis=1)
            lo[:, axis] += 1 if sign > 0 else 0
            corners = []
            for a, b in ((0, 0), (1, 0), (1, 1), (0, 1)):
                g = lo.copy()
                g[:, others[0]] += a
                g[:, others[1]] += b
                corners.append(grid_to_mesh[(g[:, 0] * (ny + 1) + g[:, 1]) * (nz + 1) + g[:, 2]])
            c00, c10, c11, c01 = corners
            tri = np.concatenate([np.stack([c00, c10, c11], axis=1),
                                  np.stack([c00, c11, c01], axis=1)])
            if np.any(tri < 0):
                raise ConfigError('internal error: chamber wall node not in mesh.')
            x = mesh.nodes
            area = np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]])
            flip = area[:, axis] * sign < 0
            tri[flip, 1], tri[flip, 2] = tri[flip, 2].copy(), tri[flip, 1].copy()
            tris.append(tri)
    return np.concatenate(tris).astype(np.int64)
