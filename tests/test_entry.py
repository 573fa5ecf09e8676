"""The Hydra entry point ``python -m codesign``: a smoke run, its outputs, exit codes, and config composition."""
from __future__ import annotations

import json
import re
import math
from pathlib import Path

import numpy as np
import pytest

from tests.cli import run_codesign as _run

REPO = Path(__file__).resolve().parent.parent
CONF = REPO / "conf"

ARTIFACTS = ["phase.npy", "psf.npy", "mtf2d.npy", "mtf_radial.npy", "phase.png", "psf_log.png", "mtf.png",
             "metrics.json"]
METRIC_KEYS = ["lsr", "lsr_smooth", "bsr", "mtf_mean", "mtf_min", "pupil_n", "pupil_pitch_m", "focal_pitch_m",
               "focal_n", "samples_per_lambda_f_over_d", "psf_energy_in_window", "phase_convention",
               "seconds_forward", "seconds_backward"]


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("entry") / "run"
    proc = _run("+experiment=psf", "debug=smoke", f"hydra.run.dir={run_dir}")
    assert proc.returncode == 0, proc.stderr[-4000:]
    return run_dir


def test_smoke_run_writes_all_artifacts(smoke_run):
    for name in ARTIFACTS:
        path = smoke_run / name
        assert path.is_file(), name
        assert path.stat().st_size > 0, name
    for name in ("phase.png", "psf_log.png", "mtf.png"):
        assert (smoke_run / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # no temporary files of the atomic writers are left behind
    assert not [p.name for p in smoke_run.iterdir() if p.name.endswith(".tmp")]


def test_smoke_run_metrics_are_sane(smoke_run):
    m = json.loads((smoke_run / "metrics.json").read_text())
    missing = [k for k in METRIC_KEYS if k not in m]
    assert not missing
    for k in METRIC_KEYS:
        if k != "phase_convention":
            assert isinstance(m[k], (int, float)) and math.isfinite(m[k]), k
    assert 0 < m["lsr"] <= 1
    assert m["lsr"] < 0.05  # the published half ring suppresses the peak strongly
    assert m["lsr_smooth"] >= m["lsr_sampled"] > 0
    assert m["lsr"] >= m["lsr_sampled"] * (1 - 1e-6)
    assert 0 < m["bsr"] <= 1 + 1e-6
    assert 0 < m["mtf_min"] <= m["mtf_mean"] <= 1
    assert 0 < m["psf_energy_in_window"] <= 1 + 1e-6
    assert m["phase_convention"] == "atan2"
    assert m["seconds_forward"] > 0 and m["seconds_backward"] > 0
    # the smoke shrink was applied
    assert m["pupil_pitch_m"] == pytest.approx(2e-5)
    assert m["focal_n"] == 160
    assert m["focal_pitch_m"] == pytest.approx(5.4e-6)
    assert m["pupil_n"] % 2 == 0 and m["pupil_n"] * m["pupil_pitch_m"] >= 3.83e-3
    lfd = m["wavelength_m"] * m["focal_length_m"] / m["aperture_diameter_m"]
    assert m["samples_per_lambda_f_over_d"] == pytest.approx(lfd / m["focal_pitch_m"], rel=1e-12)
    assert m["psf_uncoded_energy_in_window"] == pytest.approx(1.0, abs=2e-3)


def test_smoke_run_arrays_are_consistent(smoke_run):
    m = json.loads((smoke_run / "metrics.json").read_text())
    n, k = m["pupil_n"], m["focal_n"]
    phase = np.load(smoke_run / "phase.npy")
    psf = np.load(smoke_run / "psf.npy")
    mtf2d = np.load(smoke_run / "mtf2d.npy")
    radial = np.load(smoke_run / "mtf_radial.npy")
    assert phase.shape == (n, n)
    assert psf.shape == (k, k) and mtf2d.shape == (k, k)
    assert np.isfinite(phase).all() and np.isfinite(psf).all() and np.isfinite(mtf2d).all()
    assert phase.min() > -math.pi - 1e-6 and phase.max() <= math.pi + 1e-6
    assert psf.min() >= 0
    assert float(psf.astype(np.float64).sum()) == pytest.approx(m["psf_energy_in_window"], rel=1e-5)
    assert float(psf.max()) == pytest.approx(m["psf_peak"], rel=1e-6)
    # mtf2d.npy is fftshifted: DC in the centre
    assert float(mtf2d[k // 2, k // 2]) == pytest.approx(1.0, abs=1e-5)
    assert float(mtf2d.max()) <= 1 + 1e-5
    assert radial.shape[0] == 3  # freqs, coded, uncoded
    freqs, coded, uncoded = radial
    assert freqs[0] == 0 and np.all(np.diff(freqs) > 0)
    assert coded[0] == pytest.approx(1.0, abs=1e-5) and uncoded[0] == pytest.approx(1.0, abs=1e-5)
    band = (freqs > 0) & (freqs <= 0.5)
    assert float(coded[band].mean()) == pytest.approx(m["mtf_mean"], rel=1e-5)
    assert float(coded[band].min()) == pytest.approx(m["mtf_min"], rel=1e-5)


def test_missing_experiment_exits_2_listing_tasks(tmp_path, monkeypatch, capsys):
    from tests.inputs._run import config_error

    run_dir = tmp_path / "run"
    line = config_error(monkeypatch, capsys, run_dir)
    assert "task" in line and "+experiment=NAME" in line
    assert re.search(r"available: [\w, ]*\bpsf\b", line), line
    assert not run_dir.exists()


def test_bad_value_exits_2_naming_key_and_leaves_no_run_dir(tmp_path):
    run_dir = tmp_path / "run"
    proc = _run("+experiment=psf", "optics.pupil_pitch_m=-1", f"hydra.run.dir={run_dir}")
    assert proc.returncode == 2
    assert "optics.pupil_pitch_m = -1: must be a finite number > 0" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not run_dir.exists()


def test_bad_value_with_debug_smoke_exits_2(tmp_path, monkeypatch, capsys):
    # an explicit command-line value must not be silently replaced by the debug shrink (in process, with the typed
    # keys the entry point would see; the exit-code path itself: the subprocess test above)
    from tests.inputs._run import config_error

    run_dir = tmp_path / "run"
    line = config_error(monkeypatch, capsys, run_dir, "+experiment=psf", "debug=smoke", "optics.pupil_pitch_m=-1")
    assert "optics.pupil_pitch_m = -1: must be a finite number > 0" in line
    assert not run_dir.exists()


# ---- composition with Hydra's compose API ---------------------------------------------------------------------
def _group_options() -> dict[str, list[str]]:
    """Every option of every root group: the YAML files under conf/ and the nodes the spec dataclasses registered
    (codesign/config/store.py)."""
    from hydra.core.config_store import ConfigStore

    import codesign  # noqa: F401 - registers the nodes

    cs = ConfigStore.instance()
    out = {d.name: {p.stem for p in d.glob("*.yaml")} for d in sorted(CONF.iterdir()) if d.is_dir() and d.name != "hydra"}
    for group in ("optics", "mask", "sensor", "model", "data", "trainer", "metrics", "logging", "evaluate"):
        out.setdefault(group, set()).update(n.removesuffix(".yaml") for n in cs.list(group))
    return {k: sorted(v) for k, v in out.items()}


def _compose(overrides):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def test_config_groups_hold_the_expected_options():
    groups = _group_options()
    assert "psf" in groups["experiment"]
    assert {"freeform", "halfring", "pixel", "spline", "spiral", "zernike"} <= set(groups["mask"])
    assert {"sgan_b", "sgan_e", "sgan_f"} <= set(groups["model"])
    assert {"cpu", "joint_cpu", "paper"} <= set(groups["preset"])
    assert {"default", "paper"} <= set(groups["optics"])
    assert "smoke" in groups["debug"]


@pytest.mark.parametrize("group,option", [(g, o) for g, opts in _group_options().items() for o in opts])
def test_every_group_option_composes(group, option):
    from omegaconf import OmegaConf

    from codesign.config.runtime import apply_debug_overrides
    from codesign.optics import OpticsSpec
    from codesign.optics.masks import families

    prefix = "+" if group == "experiment" else ""
    overrides = [f"{prefix}{group}={option}"]
    if group != "experiment":
        overrides.append("+experiment=export" if group == "material" else "+experiment=psf")  # export's own group
    if group != "debug":
        overrides.append("debug=smoke")
    cfg = _compose(overrides)
    assert cfg.task == (option if group == "experiment" else "export" if group == "material" else "psf")
    assert apply_debug_overrides(cfg)
    spec = OpticsSpec.from_config(OmegaConf.to_container(cfg.optics, resolve=True))
    assert spec.pupil_pitch_m == pytest.approx(2e-5)
    assert cfg.mask.kind in (*families(), "freeform")


@pytest.mark.parametrize("optics", ["default", "paper"])
@pytest.mark.parametrize("mask", ["halfring", "freeform"])
def test_psf_experiment_runs_for_each_mask_and_optics(tmp_path, mask, optics):
    from codesign.experiments import run_experiment

    cfg = _compose(["+experiment=psf", "debug=smoke", f"mask={mask}", f"optics={optics}", "threads=2"])
    assert cfg.mask.kind == mask
    if optics == "paper":
        assert cfg.optics.propagator == "fft" and cfg.optics.fft_n == 4096
    lsr = run_experiment(cfg, run_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["lsr"] == pytest.approx(lsr)
    assert m["mask_kind"] == mask
    assert m["phase_convention"] == ("atan2" if mask == "halfring" else "freeform")
    # smoke size whatever the optics option (the paper's fft_n = 4096 is dropped by the shrink)
    assert m["pupil_pitch_m"] == pytest.approx(2e-5) and m["focal_n"] == 160
    assert 0 < m["lsr"] < 0.05
    for name in ARTIFACTS:
        assert (tmp_path / name).is_file(), name


def test_freeform_init_is_the_halfring_phase_as_a_plate_of_cells(tmp_path):
    """mask=freeform (the pixel family) from the published phase holds the half ring's samples; as a plate of
    cells its PSF is the half ring's times the cells' sinc^2 envelope, exactly."""
    from codesign.optics import OpticalSystem, OpticsSpec
    from codesign.experiments import run_experiment

    out = {}
    for mask in ("halfring", "freeform"):
        d = tmp_path / mask
        d.mkdir()
        cfg = _compose(["+experiment=psf", "debug=smoke", f"mask={mask}", "threads=2"])
        run_experiment(cfg, run_dir=d)
        out[mask] = {name: np.load(d / f"{name}.npy") for name in ("phase", "psf")}
    np.testing.assert_allclose(out["freeform"]["phase"], out["halfring"]["phase"], rtol=0, atol=1e-6)
    spec = OpticsSpec.from_config(cfg.optics)
    system = OpticalSystem(spec)
    envelope = system.cell_envelope(spec.pupil_pitch_m).numpy()
    np.testing.assert_allclose(out["freeform"]["psf"], out["halfring"]["psf"] * envelope, rtol=2e-4,
                               atol=1e-6 * out["halfring"]["psf"].max())


def test_run_experiment_config_error_exits_2(tmp_path, capsys):
    from codesign.experiments import run_experiment

    cfg = _compose(["+experiment=psf", "debug=smoke", "mask.convention=atan3"])
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    with pytest.raises(SystemExit) as info:
        run_experiment(cfg, run_dir=run_dir)
    assert info.value.code == 2
    assert "mask.convention = 'atan3': must be one of atan, atan2" in capsys.readouterr().err
    assert not run_dir.exists()


@pytest.mark.parametrize("task,applied", [
    ("psf", ["optics.pupil_pitch_m", "optics.focal_n", "optics.propagator", "optics.fft_n", "timing_repeats"]),
    ("restore", []),  # its optics, sensor and network sizes are the checkpoint's: nothing of debug=smoke applies
])
def test_debug_smoke_applies_and_names_only_what_the_experiment_reads(task, applied):
    """The log line "debug=smoke: applied ..." once named trainer.*, model.* and evaluate.* keys for psf."""
    from codesign.experiments import apply_debug

    cfg = _compose([f"+experiment={task}", "debug=smoke"])
    assert apply_debug(cfg) == applied


def test_every_experiment_declares_only_root_keys_it_accepts():
    from codesign.experiments import EXPERIMENTS, read_keys, root_keys

    for name in EXPERIMENTS:
        assert set(read_keys(name)) <= set(root_keys(name)), name
