"""The discrete membrane model of one array: mesh, material and boundary conditions.

A :class:`MembraneModel` binds a configuration to its mesh and quadrature data and
answers the questions the solver asks: which dofs are prescribed for a set of unit
modes, their values for given indenter displacements (eqs. 8 and 9), the Maxwell
coefficient of every element for given voltages (eq. 5), and the outputs of a state
(eqs. 7 and 10).  The optional slip correction of the frame (eq. 11) enters through
:meth:`MembraneModel.edge_stretch`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from . import kernels
from .assembly import Discretisation, PointState, SparsePattern, discretise
from .config import BIASED, DRIVEN, FREE, MODES, ArrayConfig
from .mesh import Mesh, build_mesh, geometry_key

__all__ = ["BIASED", "DRIVEN", "FREE", "MODES", "MembraneModel", "Outputs", "check_modes", "held"]


def held(mode: str) -> bool:
    """Whether a unit in ``mode`` has a rigid indenter disk (driven or biased)."""
    return mode in (DRIVEN, BIASED)


def check_modes(modes: Sequence[str], n_units: int) -> tuple[str, ...]:
    """``modes`` as a tuple if it holds ``n_units`` values out of :data:`MODES`; else ValueError."""
    modes = tuple(modes)
    if len(modes) != n_units or any(m not in MODES for m in modes):
        raise ValueError(f"modes must be {n_units} values out of {MODES}, got {list(modes)}")
    return modes

#: Sparsity patterns per mesh geometry: they depend on the connectivity only (not on
#: scale or material), and building one costs ~40 ms, so twins of one geometry with
#: other materials or scales (calibration, studies) share it.
_PATTERNS: dict[tuple, SparsePattern] = {}
_PATTERNS_SIZE = 32


def _pattern(cfg: ArrayConfig, disc: Discretisation) -> SparsePattern:
    key = geometry_key(cfg)
    if key not in _PATTERNS:
        if len(_PATTERNS) >= _PATTERNS_SIZE:
            _PATTERNS.pop(next(iter(_PATTERNS)))
        _PATTERNS[key] = SparsePattern(disc.dofs, disc.n_dofs)
    return _PATTERNS[key]


@dataclass(frozen=True)
class Outputs:
    """Per-unit outputs of an equilibrium state (SI units)."""

    force: np.ndarray
    capacitance: np.ndarray
    centre_deflection: np.ndarray
    peak_field: np.ndarray
    min_principal_stress: float


class MembraneModel:
    """Mesh, quadrature and boundary conditions of the array described by ``cfg``.

    Parameters
    ----------
    cfg : ArrayConfig
        The array.  Its mesh is built (or taken from the cache) here.
    """

    def __init__(self, cfg: ArrayConfig):
        self.cfg = cfg
        self.mesh: Mesh = build_mesh(cfg)
        self.disc: Discretisation = discretise(self.mesh)
        self.pattern = _pattern(cfg, self.disc)
        self.yeoh = cfg.yeoh
        self.thickness = cfg.thickness
        self._dofs: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        self._disks: dict[tuple, tuple[np.ndarray, ...]] = {}
        self._last_maxwell: tuple[bytes, np.ndarray] = (b"", np.zeros(0))  # (voltage's bytes, its coefficients)
        mesh = self.mesh
        #: Frame positions without slip (eq. 8): the same for every solve.
        self._frame_fixed = np.zeros((mesh.frame_nodes.size, 3))
        self._frame_fixed[:, :2] = cfg.prestretch * mesh.nodes[mesh.frame_nodes]
        self._frame_fixed.flags.writeable = False
        electrodes = [np.flatnonzero(mesh.element_unit == k) for k in range(cfg.n_units)]
        self._disk_elements = [np.flatnonzero((mesh.element_unit == k) & mesh.element_in_indenter)
                               for k in range(cfg.n_units)]
        #: Reference area [m^2] of each unit's meshed electrode.
        self.electrode_area = np.array([self.disc.weight[e].sum() for e in electrodes])
        #: Capacitance [F] of each unit in the flat pre-stretched state (det C = lp^4),
        #: the reference of ``delta_capacitance``; without slip (gamma = 1) even when
        #: a slip table is configured.
        self.flat_capacitance = cfg.permittivity / cfg.thickness * cfg.prestretch**4 * self.electrode_area
        ref = mesh.nodes[mesh.elements[:, :3]]
        e1, e2 = ref[:, 1] - ref[:, 0], ref[:, 2] - ref[:, 0]
        self._corner_area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
        #: Force scale [N] for convergence tests: t0 * c10 * D.
        self.force_scale = cfg.thickness * cfg.c10 * cfg.scaled("electrode_diameter")
        #: Length scale [m] for convergence tests: D.
        self.length_scale = cfg.scaled("electrode_diameter")

    @property
    def n_units(self) -> int:
        """Number of units."""
        return self.cfg.n_units

    def flat_state(self) -> np.ndarray:
        """Positions of the flat pre-stretched membrane, ``x = lp X, z = 0`` (shape (n_dofs,))."""
        x = np.zeros((self.mesh.n_nodes, 3))
        x[:, :2] = self.cfg.prestretch * self.mesh.nodes
        return x.ravel()

    def check_modes(self, modes: Sequence[str]) -> tuple[str, ...]:
        """Validate a per-unit mode sequence and return it as a tuple."""
        return check_modes(modes, self.n_units)

    def prescribed_dofs(self, modes: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """Sorted prescribed and free dof numbers for the given unit modes.

        Prescribed: every dof of the frame nodes (eq. 8) and of the indenter disk of
        each driven and each biased unit (eq. 9).  A biased disk's common height is an
        unknown of its own (:mod:`.indenters`), not a free dof.
        """
        key = tuple(held(m) for m in modes)
        if key not in self._dofs:  # read-only arrays, cached per pattern of held disks
            nodes = [self.mesh.frame_nodes] + [self.mesh.indenter_nodes[k] for k, m in enumerate(modes) if held(m)]
            fixed = np.unique(np.concatenate(nodes))
            dofs = (3 * fixed[:, None] + np.arange(3)).ravel()
            mask = np.ones(self.disc.n_dofs, dtype=bool)
            mask[dofs] = False
            free = np.flatnonzero(mask)
            dofs.flags.writeable = free.flags.writeable = False
            self._dofs[key] = (dofs, free)
        return self._dofs[key]

    def edge_stretch(self, modes: Sequence[str], displacement: np.ndarray) -> float:
        """Stretch of the frame along X [-]: ``lp``, or ``1 + (lp - 1) gamma`` with slip (eq. 11).

        Eq. 11 scales the X pre-stretch displacement on the outer edge by
        ``gamma(d_k)``, the configured table (:meth:`.ArrayConfig~dea_array_twin.calibration.slip`).  The paper
        only ever moves one unit; with several, gamma is taken at the largest
        ``|d_k|`` over the driven units (0 when none is driven): the frame slips as
        far as the deepest indentation pulls it, and a downward indentation pulls
        as much as the mirror upward one.  Without a table this is exactly ``lp``.

        Parameters
        ----------
        modes : sequence of str
            ``"driven"`` or ``"free"`` per unit.
        displacement : ndarray, shape (n_units,)
            Indenter displacements d_k [m] (free units ignored).
        """
        cfg = self.cfg
        if not cfg.slip_factor:
            return cfg.prestretch
        depth = max((abs(float(d)) for d, m in zip(displacement, modes) if m == DRIVEN), default=0.0)
        return 1.0 + (cfg.prestretch - 1.0) * cfg.slip(depth)

    def frame_positions(self, modes: Sequence[str], displacement: np.ndarray) -> np.ndarray:
        """Prescribed positions ``(lx X, lp Y, 0)`` of the frame nodes [m], shape (n_frame, 3).

        ``lx`` is :meth:`edge_stretch`: ``lp`` (eq. 8) or reduced by slip (eq. 11).
        """
        if not self.cfg.slip_factor:
            return self._frame_fixed  # read-only
        frame = self.mesh.frame_nodes
        out = np.zeros((frame.size, 3))
        out[:, :2] = np.array([self.edge_stretch(modes, displacement), self.cfg.prestretch]) * self.mesh.nodes[frame]
        return out

    def apply_prescribed(self, x: np.ndarray, modes: Sequence[str], displacement: np.ndarray) -> None:
        """Set the prescribed positions in ``x`` in place (eqs. 8, 9, 11).

        Frame nodes sit at :meth:`frame_positions`, ``(lx X, lp Y, 0)`` with ``lx``
        = :meth:`edge_stretch` (``lp`` without slip, eq. 8; X, Y from the membrane
        centre, where both layouts put the origin); the disk of a driven unit k at
        ``(lp X, lp Y, d_k)`` (eq. 9, no slip).  Biased disks are left alone (their
        height is an unknown: :meth:`place_disk`).
        """
        x.reshape(-1, 3)[self.mesh.frame_nodes] = self.frame_positions(modes, displacement)
        xy, xy_values, z, unit = self._driven_disks(tuple(mode == DRIVEN for mode in modes))
        x[xy] = xy_values
        x[z] = np.asarray(displacement, float)[unit]

    def _driven_disks(self, driven: tuple[bool, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The in-plane dofs of the driven units' disk nodes with their positions ``(lp X, lp Y)`` [m], their
        z dofs and each z dof's unit, cached per pattern of driven units (:meth:`apply_prescribed` in one
        assignment each, not a loop over the disks: it runs twice per warm update)."""
        if driven not in self._disks:
            units = [k for k, on in enumerate(driven) if on]
            nodes = [self.mesh.indenter_nodes[k] for k in units]
            every = np.concatenate(nodes) if nodes else np.zeros(0, dtype=int)
            xy = (3 * every[:, None] + np.arange(2)).ravel()
            xy_values = (self.cfg.prestretch * self.mesh.nodes[every]).ravel()
            unit = np.repeat(np.array(units, dtype=int), [n.size for n in nodes])
            self._disks[driven] = (xy, xy_values, 3 * every + 2, unit)
        return self._disks[driven]

    def place_disk(self, x: np.ndarray, unit: int, height: float) -> None:
        """Put the indenter disk of ``unit`` at ``(lp X, lp Y, height)`` in ``x``, in place (eq. 9)."""
        disk = self.mesh.indenter_nodes[unit]
        xs = x.reshape(-1, 3)
        xs[disk, :2] = self.cfg.prestretch * self.mesh.nodes[disk]
        xs[disk, 2] = height

    def disk_z_dofs(self, unit: int) -> np.ndarray:
        """Global z dofs of the indenter disk of ``unit`` (sorted)."""
        return 3 * self.mesh.indenter_nodes[unit] + 2

    def disk_stiffness(self, values: np.ndarray) -> np.ndarray:
        """``1_k^T K 1_j`` [N/m] over the disk z dofs of units k and j, shape (n_units, n_units).

        The stiffness of the membrane against rigid vertical motions of whole indenter
        disks with every other dof held: the ``K_ww`` block of a biased unit's height
        (:mod:`.indenters`).  ``values`` are the tangent's nonzeros in :attr:`pattern` order.
        """
        dofs, indicator = self._disk_indicator
        return indicator.T @ (self.pattern.block(values, dofs, dofs) @ indicator)

    @functools.cached_property
    def _disk_indicator(self) -> tuple[np.ndarray, np.ndarray]:
        """Every disk z dof (sorted) and, per dof, a one in its unit's column."""
        owner = np.full(self.disc.n_dofs, -1)
        for k in range(self.n_units):
            owner[self.disk_z_dofs(k)] = k
        dofs = np.flatnonzero(owner >= 0)
        return dofs, (owner[dofs, None] == np.arange(self.n_units)).astype(float)

    def corner_area_stretch(self, positions: np.ndarray) -> np.ndarray:
        """Area ratio (deformed / reference) of each element's corner triangle [-], shape (n_elements,).

        The flat-triangle view of the membrane that a visualisation draws; ``positions``
        are the node positions, shape (n_nodes, 3) [m].
        """
        tri = positions[self.mesh.elements[:, :3]]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        return area / self._corner_area

    def energy(self, point: PointState, voltage: np.ndarray) -> float:
        """Stored energy ``t0 sum_q w_q Psi`` [J] of a point state."""
        return kernels.energy(self.disc, point, self.yeoh, self.maxwell(voltage), self.thickness)

    def maxwell(self, voltage: np.ndarray) -> np.ndarray:
        """Per element ``k = 0.5 eps0 epsr (V/t0)^2`` [Pa] of its unit, 0 on passive membrane (read-only).

        The last voltage's array is kept: consecutive solves at one voltage share it."""
        voltage = np.asarray(voltage, float)
        key, last = self._last_maxwell
        if key == voltage.tobytes():
            return last
        unit = self.mesh.element_unit
        per_unit = 0.5 * self.cfg.permittivity * (voltage / self.thickness) ** 2
        out = np.where(unit >= 0, np.append(per_unit, 0.0)[unit], 0.0)
        out.flags.writeable = False
        self._last_maxwell = (voltage.tobytes(), out)
        return out

    def outputs(self, x: np.ndarray, forces: np.ndarray, point: PointState, voltage: np.ndarray,
                modes: Sequence[str]) -> Outputs:
        """Per-unit force (eq. 10), capacitance (eq. 7), centre deflection, peak field.

        ``forces`` is the internal force vector at ``x`` and ``point`` its point
        state; the force on a driven indenter is the sum of the z components over its
        disk nodes.  The minimum principal Cauchy stress is taken over the membrane
        outside driven disks.
        """
        mesh, cfg = self.mesh, self.cfg
        cap, peak = kernels.electrode_sums(self.disc, point, self.n_units)
        z = forces.reshape(-1, 3)[:, 2]
        force = np.zeros(self.n_units)
        in_disks = np.zeros(mesh.n_elements, dtype=bool)
        for k, mode in enumerate(modes):
            if held(mode):
                force[k] = z[mesh.indenter_nodes[k]].sum()
                in_disks[self._disk_elements[k]] = True
        cap *= cfg.permittivity / cfg.thickness
        peak = np.sqrt(peak) * np.abs(np.asarray(voltage, float)) / cfg.thickness
        sigma_min = kernels.min_principal_stress(point, in_disks)
        centre = x.reshape(-1, 3)[mesh.centre_nodes, 2]
        return Outputs(force, cap, centre, peak, sigma_min)
