"""The camera as one differentiable object: mask -> phase -> PSF (optics window) -> pixel kernel -> sensor image, and
the kernel's OTF on the network's padded grid (what a Wiener stage needs).

The same object serves a frozen mask (training a restorer, evaluating, restoring captures) and a trainable one
(co-design): while the mask is frozen its optics are computed once and cached, keyed by the mask's parameter
values; while it is trainable every call recomputes them with the mask's graph, so that one backward pass from a
restoration loss reaches the mask parameters.

A camera with a measured PSF (``optics.psf_file``, codesign/optics/measured.py) puts it in place of the mask's
computed window PSF in every PSFState it makes, so that the kernels, the OTF of a Wiener stage and every simulated
image use it; the mask stays frozen (its computed PSF registers the measured one and is reported beside it), and
the laser's halo beyond the window, computed from the mask's far field, is left out.
"""
from __future__ import annotations

import copy
import logging
from dataclasses import dataclass

import torch

from codesign.errors import ConfigError
from codesign.optics.far_field import far_psf
from codesign.optics.masks import Mask
from codesign.optics.measured import OUTSIDE_WARN, MeasuredPSF, Placement
from codesign.optics.psf import OpticalSystem
from codesign.sensor.halo import LaserHalo
from codesign.sensor.kernels import otf_from_kernel
from codesign.sensor.simulator import (
    PSFState,
    SensorSimulator,
    mask_state_key,
    psf_state,
)

log = logging.getLogger("codesign.camera")


@dataclass
class OpticsOutputs:
    """What the rest of the chain needs of the optics for one set of mask parameters.

    state: the window PSF and its uncoded normalizers (sensor simulation); kernel: the PSF integrated over one
    network pixel, (k, k); otf: rfft2 of that kernel on the padded grid, (P, P // 2 + 1); key: cache key of the
    mask's values (None while the mask trains); phase: the pupil phase they came from (None for a measured PSF,
    which the phase does not describe).
    """

    state: PSFState
    kernel: torch.Tensor
    otf: torch.Tensor
    key: tuple | None = None
    phase: torch.Tensor | None = None


class Camera(torch.nn.Module):
    """An OpticalSystem, a Mask on its pupil grid and a SensorSimulator, with the optics of the current mask.

    Args:
        system: the optical system (pupil grid, propagator); mask: any Mask built on ``system.grid``;
        simulator: the sensor model (its optics spec must be ``system.spec``); device: where OTFs live;
        measured: a measured PSF that replaces the mask's computed one (the mask then stays frozen), or None;
        laser_line: a LaserLines holding the laser's one line when it is not the design wavelength
        (sensor.wavelength_laser_m), or None: the laser then has its own PSF there (PSFState.laser);
        scene_spectrum: (LaserLines of the scene's wavelengths, their weights) of optics.scene_spectrum, or None:
        the scene's PSF is then the weighted mean of the mask's PSFs there, the laser's its own line's.
    """

    def __init__(self, system: OpticalSystem, mask: Mask, simulator: SensorSimulator,
                 device: torch.device | str = "cpu", measured: MeasuredPSF | None = None, laser_line=None,
                 scene_spectrum: tuple | None = None):
        super().__init__()
        self.system, self.mask, self.simulator = system, mask, simulator
        self.laser_line, self.scene_spectrum = laser_line, scene_spectrum
        self.device = torch.device(device)
        self.measured = measured
        self.placement: Placement | None = None  # the measured PSF on the window, at the last optics evaluation
        self.design_psf: torch.Tensor | None = None  # the mask's computed window PSF it replaced there
        self._warned: tuple | None = None
        self.mask_forward = mask  # called for the phase; a DistributedDataParallel wrapper may take its place
        self.trainable = False
        self._frozen: OpticsOutputs | None = None
        # a frozen mask's halos: {"halo" (the design wavelength's) / "line_halo" (the laser line's): (key, LaserHalo)}
        self._halo_frozen: dict | None = None
        self._halo_train: dict | None = None  # a training mask's: age (optics evaluations), values, LaserHalo
        # a frozen camera of the same mask on a sensor at least as large whose halo this one reuses (a restorer's
        # pool at several pixel scales: the far PSF, seconds per mask, is the same light on any pixel grid)
        self.halo_donor: Camera | None = None
        self.set_trainable(False)

    # ---- geometry ---------------------------------------------------------------------------------------------
    @property
    def sensor(self):
        """The SensorSpec."""
        return self.simulator.sensor

    @property
    def optics(self):
        """The OpticsSpec."""
        return self.system.spec

    @property
    def image_size(self) -> int:
        """Side of the network's image in pixels (data.image_size, e.g. 256): the sensor simulated or binned to it."""
        return self.simulator.sensor.image_size

    @property
    def padded_size(self) -> int:
        """Side of the zero-padded grid the OTF and the Wiener deconvolution live on (data.padded_size, e.g. 384)."""
        return self.simulator.sensor.padded_size

    @property
    def scene_size(self) -> int:
        """Side of the scene crop a simulation needs (the padded grid plus the kernel's reach)."""
        return self.simulator.scene_size

    def check_padding(self) -> None:
        """The padded grid must hold the field plus the PSF's reach, or the (circular) Wiener deconvolution of a
        restorer and of the baselines wraps the blur of one border onto the other."""
        s, k = self.simulator.sensor, self.simulator.coarse.ksize
        need = s.image_size + k - 1
        if s.padded_size < need:
            raise ConfigError("data.padded_size", s.padded_size, f"must be >= data.image_size + PSF kernel - 1 = "
                              f"{s.image_size} + {k} - 1 = {need} at this pitch, so that deconvolution does not wrap")

    @property
    def halo_on(self) -> bool:
        """Whether a laser's light beyond the window is simulated: sensor.laser_halo, and no measured PSF."""
        return self.simulator.sensor.laser_halo and self.measured is None

    # ---- the mask ---------------------------------------------------------------------------------------------
    def set_trainable(self, flag: bool) -> None:
        """Let the mask's parameters take gradients (co-design) or freeze them (cached optics)."""
        if flag and self.measured is not None:
            raise ConfigError("optics.psf_file", self.measured.path, "a measured PSF fixes the optics: the mask "
                              "cannot be trained through it (leave optics.psf_file null to co-design the mask)")
        self.trainable = bool(flag)
        for p in self.mask.parameters():
            p.requires_grad_(self.trainable)

    def invalidate(self) -> None:
        """The mask's values changed: recompute the cached optics on next use."""
        self._frozen = None

    def release_simulation_cache(self) -> None:
        """Drop the simulator's kept kernels and PSF spectra, and a laser line's, keeping the optics (PSF, OTF) and
        the laser halo: a camera that is not imaging for a while holds tens of MB less (a restorer's pool of many)."""
        self.simulator.release_cache()
        laser = self._frozen.state.laser if self._frozen is not None else None
        if laser is not None:
            laser.kernels.clear()

    def use_mask(self, mask: Mask) -> None:
        """Image through ``mask`` from now on, frozen; a mask built on another pupil grid (a search on a coarser
        one) is sampled onto this camera's by its family (Mask.on_grid)."""
        if self.measured is not None:
            raise ConfigError("optics.psf_file", self.measured.path, "a measured PSF fixes the optics: a camera "
                              "with one images through no other mask")
        grid = self.system.grid
        if mask.grid.n != grid.n or abs(mask.grid.pitch - grid.pitch) > 1e-12 * grid.pitch:
            mask = mask.on_grid(grid, self.system.spec.aperture_diameter_m)
        self.mask = self.mask_forward = mask.to(grid.rho.device)
        self.set_trainable(False)
        self._frozen, self._halo_frozen = None, None

    # ---- the optics -------------------------------------------------------------------------------------------
    def optics_of(self, phase: torch.Tensor, key: tuple | None = None) -> OpticsOutputs:
        """PSF state, network-pitch kernel and padded-grid OTF of a pupil phase; all carry the phase's graph.
        ``key``: the cache key of a frozen mask's values (the simulator then keeps the kernels for its images)."""
        cell = self.mask.plate_cell_m
        state = psf_state(self.system, phase, cell)
        if self.measured is not None:
            state = self._measured_state(state)
        state.halo = self._halo_source(key) if self.halo_on else None
        if self.laser_line is not None and self.measured is None:
            system = self.laser_line.systems[0]
            state.laser = psf_state(system, self.laser_line.phase(phase, 0), cell)
            state.laser.halo = self._halo_source(key, line=True) if self.halo_on else None
        if self.scene_spectrum is not None:  # the scene's band; the laser keeps its line's state (made above)
            laser = state.laser if state.laser is not None else state
            state = spectral_state(*self.scene_spectrum, phase, cell)
            state.laser = laser
        kernel = self.simulator.kernel(state, key=key)
        return OpticsOutputs(state, kernel, otf_from_kernel(kernel, self.padded_size).to(self.device), key,
                             phase if self.measured is None else None)

    def _measured_state(self, design: PSFState) -> PSFState:
        """The PSFState of the measured PSF, registered on the mask's computed one (``design``), which it replaces;
        the uncoded normalizers are the optical system's (the LSR of a measured PSF is its peak / h0(0)). No halo:
        the light beyond a measured frame is not known."""
        psf = design.psf.detach()
        placed = self.measured.place(self.system.spec, psf.to(torch.float64).cpu().numpy())
        self.design_psf, self.placement = psf, placed
        if placed.outside > OUTSIDE_WARN and self._warned != (placed.shift, round(placed.outside, 6)):
            self._warned = (placed.shift, round(placed.outside, 6))
            spec = self.system.spec
            log.warning("optics.psf_file: %.2f%% of the measured frame's light falls beyond the %d x %d optics window "
                        "(%.3g mm) and is lost to the window PSF (the scene's share returns as the uniform veil, the "
                        "laser's is dropped); a larger optics.focal_n keeps it", 100 * placed.outside, spec.focal_n,
                        spec.focal_n, spec.focal_extent_m * 1e3)
        return PSFState(psf=torch.from_numpy(placed.psf).to(dtype=psf.dtype, device=psf.device),
                        uncoded_peak=design.uncoded_peak, uncoded_energy=design.uncoded_energy, halo=None)

    def _halo_source(self, key: tuple | None, line: bool = False):
        """A callable giving the LaserHalo of the mask, computed on first call (only a laser needs it). A frozen
        mask's is kept under its values' key. While the mask trains, every optics evaluation (training steps and
        validations alike) uses the halo of the mask as it was at the last refresh, recomputed every
        sensor.halo_refresh evaluations: the far PSF takes seconds and carries no gradient, and the mask moves
        little in between. That schedule and the refresh's mask values are in ``halo_state`` (the checkpoint), so
        a resumed run uses the halo an uninterrupted one uses."""
        slot = "line_halo" if line else "halo"
        if self.trainable:
            t = self._halo_train
            if line and t is not None:  # the design halo's call below (made first) set this evaluation's snapshot
                return lambda: self._training_halo(t, slot)
            if t is not None and t["age"] < self.simulator.sensor.halo_refresh:
                t["age"] += 1
                return lambda: self._training_halo(t, slot)
            snapshot = {k: v.detach().clone() for k, v in self.mask.state_dict().items()}
            self._halo_train = t = {"age": 1, "values": snapshot, "halo": None, "line_halo": None}
            return lambda: self._training_halo(t, slot)
        frozen = self._halo_frozen.get(slot) if self._halo_frozen is not None else None
        if frozen is not None and frozen[0] == key and key is not None:
            halo = frozen[1]
            return lambda: halo
        cell: list = []

        def compute():
            if not cell:
                donor = self.halo_donor
                cell.append(donor._halo_source(key, line)() if donor is not None else self._far_halo(self.mask, line))
                self._halo_frozen = {**(self._halo_frozen or {}), slot: (key, cell[0])}
            return cell[0]
        return compute

    def _training_halo(self, t: dict, slot: str = "halo") -> LaserHalo:
        if t.get(slot) is None:
            source = copy.deepcopy(self.mask)
            source.load_state_dict(t["values"])
            t[slot] = self._far_halo(source, slot == "line_halo")
        return t[slot]

    def _far_halo(self, mask, line: bool = False) -> LaserHalo:
        """The LaserHalo of ``mask`` at the design wavelength, or (``line``) at the laser's line."""
        spec, m = self.system.spec, self.system.spec.focal_n
        phase_map = None
        if line:
            spec, phase_map = self.laser_line.systems[0].spec, lambda ph: self.laser_line.phase(ph, 0)
        far, pitch = far_psf(mask, spec, self.simulator.sensor.side_m, self.system.dtype, phase_map=phase_map)
        window = ((-(m // 2) - 0.5) * spec.focal_pitch_m, (m - m // 2 - 0.5) * spec.focal_pitch_m)
        return LaserHalo(far, pitch, window)

    def halo_state(self) -> dict | None:
        """What a checkpoint keeps of a training mask's halo: its age and the mask values it came from."""
        t = self._halo_train
        return None if t is None else {"age": t["age"], "values": t["values"]}

    def load_halo_state(self, state: dict | None) -> None:
        """Restore what ``halo_state`` kept (None: no training halo); the halos themselves are recomputed from the
        stored mask values when next needed."""
        self._halo_train = None if state is None else {"age": int(state["age"]), "values": state["values"],
                                                       "halo": None, "line_halo": None}

    def current_optics(self) -> OpticsOutputs:
        """The optics of the mask's current values: with the mask's graph while it is trainable (recomputed every
        call), else cached without gradient."""
        if self.trainable:
            return self.optics_of(self.mask_forward())
        return self.frozen_optics()

    def frozen_optics(self) -> OpticsOutputs:
        """The optics of the mask's current values without gradient (cached), whatever ``trainable`` says."""
        if self._frozen is None:
            with torch.no_grad():
                self._frozen = self.optics_of(self.mask.phase(), mask_state_key(self.mask))
        return self._frozen

    @property
    def otf(self) -> torch.Tensor:
        """OTF of the mask's current values on the padded grid, no gradient."""
        return self.frozen_optics().otf

    # ---- the sensor -------------------------------------------------------------------------------------------
    def forward(self, scenes: torch.Tensor, params, seed: int, optics: OpticsOutputs | None = None) -> dict:
        """Simulate a batch (see SensorSimulator.forward for the outputs).

        ``optics``: None = the frozen, cached optics (no gradient, kernels cached by the simulator); an
        OpticsOutputs from ``current_optics()`` of a trainable mask carries its graph into the sensor image.
        """
        if optics is None:
            frozen = self.frozen_optics()
            with torch.no_grad():
                return self.simulator(scenes, params, frozen.state, seed=seed, mask_key=frozen.key)
        return self.simulator(scenes, params, optics.state, seed=seed, mask_key=None)


def spectral_state(lines, weights: tuple, phase: torch.Tensor, cell_m: float | None) -> PSFState:
    """The scene's PSFState over a band: the weighted mean of the mask's PSFs at ``lines``' wavelengths (the surface
    seen at each) and of their uncoded normalizers (a uniform scene then keeps its level through the uncoded lens)."""
    total = float(sum(weights))
    states = [psf_state(system, lines.phase(phase, i), cell_m) for i, system in enumerate(lines.systems)]
    return PSFState(psf=sum(w * st.psf for w, st in zip(weights, states)) / total,
                    uncoded_peak=sum(w * st.uncoded_peak for w, st in zip(weights, states)) / total,
                    uncoded_energy=sum(w * st.uncoded_energy for w, st in zip(weights, states)) / total)


def field_of_view(x: torch.Tensor, n: int) -> torch.Tensor:
    """The central n x n of a padded (..., P, P) map: the sensor's field of view (the simulator pads it
    symmetrically, (P - n) // 2 before)."""
    p = x.shape[-1]
    m = (p - n) // 2
    return x[..., m:m + n, m:m + n]
