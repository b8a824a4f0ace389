"""Triangle meshes of the membrane, made with gmsh and cached per geometry.

Every circle (electrode edge, indenter edge, circular frame) is a curve of the
geometry, so element edges follow it; quadratic elements put their mid-edge nodes on
it (curved edges).  Each element carries the unit whose electrode covers it (``-1`` on
the passive membrane) and whether it lies in that unit's indenter disk.  A node sits
at each unit centre, where the centre deflection is read.
"""

from __future__ import annotations

import dataclasses
import threading
from dataclasses import dataclass

import numpy as np

from .config import ArrayConfig
from .geometry import unit_centres

_GMSH_LOCK = threading.Lock()
_CACHE: dict[tuple, "Mesh"] = {}
_CACHE_SIZE = 32


@dataclass(frozen=True)
class Mesh:
    """A membrane mesh in the reference plane.

    Attributes
    ----------
    nodes : ndarray, shape (n_nodes, 2)
        Reference coordinates X, Y [m], origin at the membrane centre.
    elements : ndarray, shape (n_elements, 3 or 6)
        Node indices in gmsh order.
    order : int
        Element order (1 or 2).
    element_unit : ndarray, shape (n_elements,)
        Unit whose electrode covers the element, ``-1`` for passive membrane.
    element_in_indenter : ndarray of bool, shape (n_elements,)
        Whether the element lies in its unit's indenter disk.
    frame_nodes : ndarray
        Nodes on the outer edge, clamped by the frame (eq. 8).
    indenter_nodes : tuple of ndarray
        Per unit, the nodes of its indenter disk (prescribed when driven, eq. 9).
    centre_nodes : ndarray, shape (n_units,)
        The node at each unit centre.
    """

    nodes: np.ndarray
    elements: np.ndarray
    order: int
    element_unit: np.ndarray
    element_in_indenter: np.ndarray
    frame_nodes: np.ndarray
    indenter_nodes: tuple
    centre_nodes: np.ndarray

    @property
    def n_nodes(self) -> int:
        """Number of nodes."""
        return self.nodes.shape[0]

    @property
    def n_elements(self) -> int:
        """Number of triangles."""
        return self.elements.shape[0]


def geometry_key(cfg: ArrayConfig) -> tuple:
    """The config fields that determine the unscaled mesh (the cache key)."""
    return (cfg.layout, cfg.rows, cfg.cols, cfg.length, cfg.width, cfg.frame_radius, cfg.electrode_diameter,
            cfg.spacing, cfg.indenter_radius, cfg.electrode_shape, cfg.element_order, cfg.mesh_size,
            cfg.mesh_size_indenter, cfg.mesh_size_electrode)


def build_mesh(cfg: ArrayConfig) -> Mesh:
    """Mesh the membrane of ``cfg``.

    The geometry is meshed at ``scale = 1`` once per process (cached) and the nodes
    are then multiplied by ``scale``, so scaled arrays have exactly similar meshes.
    """
    key = geometry_key(cfg)
    with _GMSH_LOCK:
        if key not in _CACHE:
            if len(_CACHE) >= _CACHE_SIZE:
                _CACHE.pop(next(iter(_CACHE)))
            _CACHE[key] = _mesh_with_gmsh(cfg.replace(scale=1.0))
        mesh = _CACHE[key]
    if cfg.scale == 1.0:
        return mesh
    return dataclasses.replace(mesh, nodes=mesh.nodes * cfg.scale)


def _mesh_with_gmsh(cfg: ArrayConfig) -> Mesh:
    import gmsh  # imported here: only meshing needs it

    centres = unit_centres(cfg)
    radius = 0.5 * cfg.scaled("electrode_diameter")
    r_ind = cfg.scaled("indenter_radius")
    h_far, h_ind = cfg.scaled("mesh_size"), cfg.scaled("mesh_size_indenter")
    h_el = cfg.scaled("mesh_size_electrode")
    gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("membrane")
        occ = gmsh.model.occ
        if cfg.layout == "circular":
            frame = occ.addDisk(0, 0, 0, cfg.scaled("frame_radius"), cfg.scaled("frame_radius"))
        else:
            L, H = cfg.scaled("length"), cfg.scaled("width")
            frame = occ.addRectangle(-0.5 * L, -0.5 * H, 0, L, H)
        electrodes, indenters = [], []
        for cx, cy in centres:
            if cfg.electrode_shape == "circle":
                electrodes.append(occ.addDisk(cx, cy, 0, radius, radius))
            else:
                a = cfg.square_side
                electrodes.append(occ.addRectangle(cx - 0.5 * a, cy - 0.5 * a, 0, a, a))
            indenters.append(occ.addDisk(cx, cy, 0, r_ind, r_ind))
        tools = [(2, t) for t in electrodes + indenters]
        _, pieces = occ.fragment([(2, frame)], tools)
        occ.synchronize()
        frame_pieces = {t for _, t in pieces[0]}
        electrode_pieces = [{t for _, t in p} for p in pieces[1:1 + len(electrodes)]]
        indenter_pieces = [{t for _, t in p} for p in pieces[1 + len(electrodes):]]
        surfaces: dict[int, tuple[int, bool]] = {}
        for k in range(len(centres)):
            for tag in electrode_pieces[k]:
                surfaces[tag] = (k, tag in indenter_pieces[k])
        for tag in frame_pieces - set(surfaces):
            surfaces[tag] = (-1, False)
        centre_points = []
        for k, (cx, cy) in enumerate(centres):
            (tag,) = indenter_pieces[k]
            point = occ.addPoint(cx, cy, 0)
            occ.synchronize()
            gmsh.model.mesh.embed(0, [point], 2, tag)
            centre_points.append(point)
        boundary = gmsh.model.getBoundary([(2, t) for t in frame_pieces], oriented=False)
        frame_curves = [abs(t) for _, t in boundary]
        indenter_curves = [abs(t) for k in range(len(centres)) for s in indenter_pieces[k]
                           for _, t in gmsh.model.getBoundary([(2, s)], oriented=False)]
        electrode_curves = [abs(t) for k in range(len(centres)) for s in electrode_pieces[k]
                            for _, t in gmsh.model.getBoundary([(2, s)], oriented=False)]
        field = gmsh.model.mesh.field
        sizes = [_threshold(field, indenter_curves, h_ind, h_far, 2.0 * radius),
                 _threshold(field, sorted(set(electrode_curves) - set(indenter_curves)), h_el, h_far, radius)]
        smallest = field.add("Min")
        field.setNumbers(smallest, "FieldsList", sizes)
        field.setAsBackgroundMesh(smallest)
        for name in ("Mesh.MeshSizeExtendFromBoundary", "Mesh.MeshSizeFromPoints", "Mesh.MeshSizeFromCurvature"):
            gmsh.option.setNumber(name, 0)
        gmsh.option.setNumber("Mesh.Algorithm", 6)
        gmsh.option.setNumber("Mesh.ElementOrder", cfg.element_order)
        gmsh.option.setNumber("Mesh.HighOrderOptimize", 0)
        gmsh.model.mesh.generate(2)
        return _collect(gmsh, cfg, surfaces, frame_curves, indenter_pieces, centre_points)
    finally:
        gmsh.finalize()


def _threshold(field, curves: list[int], size_min: float, size_max: float, reach: float) -> int:
    """A size field growing linearly from ``size_min`` on ``curves`` to ``size_max`` at ``reach``."""
    dist = field.add("Distance")
    field.setNumbers(dist, "CurvesList", curves)
    field.setNumber(dist, "Sampling", 200)
    thr = field.add("Threshold")
    field.setNumber(thr, "InField", dist)
    field.setNumber(thr, "SizeMin", size_min)
    field.setNumber(thr, "SizeMax", size_max)
    field.setNumber(thr, "DistMin", 0.0)
    field.setNumber(thr, "DistMax", reach)
    return thr


def _collect(gmsh, cfg, surfaces, frame_curves, indenter_pieces, centre_points) -> Mesh:
    """Read nodes, elements and region tags out of the gmsh model."""
    tags, coords, _ = gmsh.model.mesh.getNodes()
    index = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    index[tags.astype(np.int64)] = np.arange(tags.size)
    nodes = coords.reshape(-1, 3)[:, :2].copy()
    gtype = 2 if cfg.element_order == 1 else 9
    nen = 3 if cfg.element_order == 1 else 6
    blocks, units, inside = [], [], []
    for surface, (unit, is_indenter) in sorted(surfaces.items()):
        _, node_tags = gmsh.model.mesh.getElementsByType(gtype, surface)
        conn = index[node_tags.astype(np.int64)].reshape(-1, nen)
        blocks.append(conn)
        units.append(np.full(conn.shape[0], unit))
        inside.append(np.full(conn.shape[0], is_indenter))
    elements = np.vstack(blocks)
    # Orient every triangle counter-clockwise (positive reference Jacobian).
    p = nodes[elements[:, :3]]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    cross = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    flip = cross < 0
    swap = [0, 2, 1, 5, 4, 3] if nen == 6 else [0, 2, 1]
    elements[flip] = elements[flip][:, swap]
    frame_nodes = np.unique(np.concatenate([
        index[gmsh.model.mesh.getNodes(1, c, includeBoundary=True)[0].astype(np.int64)] for c in frame_curves]))
    element_unit = np.concatenate(units)
    element_in_indenter = np.concatenate(inside)
    indenter_nodes = tuple(np.unique(elements[(element_unit == k) & element_in_indenter])
                           for k in range(len(indenter_pieces)))
    centre_nodes = np.array([index[int(gmsh.model.mesh.getNodes(0, pt)[0][0])] for pt in centre_points])
    used = np.unique(elements)
    if used.size != nodes.shape[0]:
        # gmsh keeps geometry nodes that no triangle uses; renumber to drop them.
        remap = np.full(nodes.shape[0], -1, dtype=np.int64)
        remap[used] = np.arange(used.size)
        nodes, elements = nodes[used], remap[elements]
        frame_nodes = remap[frame_nodes][remap[frame_nodes] >= 0]
        indenter_nodes = tuple(remap[n] for n in indenter_nodes)
        centre_nodes = remap[centre_nodes]
    return Mesh(nodes, elements, cfg.element_order, element_unit, element_in_indenter,
                frame_nodes, indenter_nodes, centre_nodes)
