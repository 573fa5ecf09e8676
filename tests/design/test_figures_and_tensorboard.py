"""Issue 39, item 5: the mask search's figures and TensorBoard events say what they show (the Pareto plot's axis
fits its data and its legend names every series, the searched design is marked; the PSF figure's colour bar labels
keep clear of the next panel; a search logs its progress and the best design's images)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from codesign.design.tradeoff_figures import evaluations_figure
from codesign.io.plots import plt, psf_figure


class _Limit:
    uncoded_mtf_mean = 0.3

    @staticmethod
    def lsr_limit(m, energy=None):
        return 0.05 * m ** 2


def _ev(m, lsr, feasible):
    return SimpleNamespace(mtf_mean=m, lsr_sampled=lsr, feasible=feasible)


def test_pareto_axis_fits_the_data_and_every_legend_entry_names_something():
    evs = [_ev(0.05 + 0.004 * i, 0.01 + 0.001 * i, False) for i in range(10)]  # nothing feasible: no empty entry
    sweeps = [SimpleNamespace(problem=SimpleNamespace(records=evs))]
    front = [{"feasible": False, "mtf_floor": 0.07, "mtf_mean": 0.08, "lsr": 0.012}]
    base = {"mtf_mean": 0.07, "lsr": 0.011}
    fig = evaluations_figure(sweeps, front, base, _Limit(), "sampled")
    try:
        ax = fig.axes[0]
        lo, hi = ax.get_xlim()
        assert 0.086 < hi < 0.095 and 0.04 < lo < 0.05  # data from 0.05 to 0.086, a small margin
        handles, labels = ax.get_legend_handles_labels()
        assert all(label.strip() for label in labels)
        for h in handles:  # every entry draws something
            data = h.get_offsets() if hasattr(h, "get_offsets") else h.get_xydata()
            assert len(data) > 0, h.get_label()
        assert any("floor" in label for label in labels)  # the dotted floor line is explained
    finally:
        plt.close(fig)
    fig = evaluations_figure(sweeps, front, base, _Limit(), "sampled", best={"mtf_mean": 0.086, "lsr": 0.0105})
    try:
        handles, labels = fig.axes[0].get_legend_handles_labels()
        marked = [h for h in handles if "searched" in h.get_label()]  # the searched design is marked
        assert len(marked) == 1 and tuple(marked[0].get_xydata()[0]) == (0.086, 0.0105)
    finally:
        plt.close(fig)


def _overlap(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


def test_psf_figure_colour_bar_label_clear_of_the_next_panel():
    yy, xx = np.mgrid[-64:64, -64:64]
    psf0 = np.exp(-(xx ** 2 + yy ** 2) / 8.0)
    psf0 /= psf0.sum()
    fig = psf_figure(np.roll(psf0, 5, axis=1), psf0, 6.5e-6, "test")
    try:
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        bars = [a for a in fig.axes if a.get_ylabel().startswith("log10")]
        panels = [a for a in fig.axes if a.get_ylabel() == "y [mm]"]
        assert len(bars) == 2 and len(panels) == 2
        left_bar = min(bars, key=lambda a: a.get_position().x0)
        right_panel = max(panels, key=lambda a: a.get_position().x0)
        label = left_bar.yaxis.label.get_window_extent(renderer)
        for item in (right_panel.yaxis.label, *right_panel.get_yticklabels()):
            assert not _overlap(label, item.get_window_extent(renderer)), item.get_text()
    finally:
        plt.close(fig)


def test_smoke_search_logs_its_progress_and_the_best_design_s_images(mask_search_smoke):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run_dir, _ = mask_search_smoke
    acc = EventAccumulator(str(run_dir), size_guidance={"scalars": 0, "images": 0})
    acc.Reload()
    scalars, images = set(acc.Tags()["scalars"]), set(acc.Tags()["images"])
    for tag in ("search/objective", "search/constraint/mtf", "search/lsr_sampled", "search/lsr_smooth",
                "search/mtf_mean", "search/violation", "best/lsr", "best/mtf_mean", "published/lsr"):
        assert tag in scalars, (tag, sorted(scalars))
    assert len(acc.Scalars("search/objective")) == 16  # every evaluation: 2 starts x 8
    assert {"best/phase", "best/psf_log10"} <= images, sorted(images)


def test_sensor_grids_have_a_colour_bar_in_dn():
    from codesign.experiments.simulate import _grid_figure

    grid = np.random.default_rng(0).uniform(1, 1000, size=(2, 2, 16, 16))
    for log_view in (False, True):
        fig = _grid_figure(grid, ["a", "b"], [0.0, 1e6], log_view, 1000.0)
        try:
            bars = [a for a in fig.axes if "DN" in a.get_ylabel()]
            assert len(bars) == 1, [a.get_ylabel() for a in fig.axes]
            assert bars[0].get_ylabel().startswith("log10") == log_view
        finally:
            plt.close(fig)


def test_settings_stay_out_of_the_scalars(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from codesign.io.tensorboard import log_summary, open_writer

    metrics = {"lsr": 0.01, "mtf_mean": 0.08, "pupil_n": 202, "focal_pitch_m": 6.5e-6, "threads": 2,
               "wavelength_m": 5.32e-7, "feasible": True, "table": [1, 2]}
    def scalars(run: str) -> set:
        acc = EventAccumulator(str(tmp_path / run), size_guidance={"scalars": 0})
        acc.Reload()
        return set(acc.Tags()["scalars"])

    log_summary(open_writer(tmp_path / "a"), {"mask": "halfring"}, metrics)
    assert scalars("a") == {"final/lsr", "final/mtf_mean"}  # the grid, the optics, the threads: settings
    log_summary(open_writer(tmp_path / "b"), {"mask": "halfring"}, {**metrics, "r_1": 3.0}, settings=("r_1",))
    assert scalars("b") == {"final/lsr", "final/mtf_mean"}  # and the caller's own (a fixed mask's parameters)


def test_joint_logs_the_test_scores_per_laser_strength_as_scalars(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from codesign.experiments.joint import _hparams
    from codesign.io.tensorboard import open_writer

    table = {"sensor": {"psnr": 10.0}, "wiener": {"psnr": 12.0}, "sgan": {"psnr": 20.0, "psnr_matched": 21.0,
                                                                         "ssim": 0.5, "ssim_matched": 0.6}}
    metrics = {"network": "n", "variant": "v", "size": "s", "mask_kind": "halfring", "steps": 4, "lsr_max": 0.01, "psnr": 20.0,
               "evaluation": {"laser_0": table, "laser_1e6": table, "H1": table},
               "evaluation_published": {"laser_1e6": table}}
    _hparams(open_writer(tmp_path), None, metrics, "sgan")
    acc = EventAccumulator(str(tmp_path), size_guidance={"scalars": 0})
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    assert {"test/psnr/alpha_l_0", "test/psnr/alpha_l_1e6", "test/psnr_matched/alpha_l_1e6", "test/psnr/stage_H1",
            "test_published/psnr/alpha_l_1e6"} <= tags, sorted(tags)
    assert acc.Scalars("test/psnr/alpha_l_1e6")[0].value == 20.0


def _images(n=2, size=16, names=("sensor", "wiener", "sgan")):
    import torch

    g = torch.Generator().manual_seed(0)
    return {k: torch.rand(n, 1, size, size, generator=g) for k in ("input", *names)}


def test_evaluation_panel_explains_its_preset_columns_and_psnr():
    import torch

    from codesign.train.evaluation import panel_figure

    images = _images()
    table = {k: {"psnr": 20.0} for k in ("sensor", "wiener", "sgan")}
    fig = panel_figure(images, torch.rand(2, 1, 16, 16), ["cell", "chelsea"], "H1", table)
    try:
        titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
        assert not {"input", "sensor", "wiener", "sgan", "truth"} & set(titles), titles  # no code names
        assert any("classical Wiener" in t for t in titles) and any("ground truth" in t for t in titles)
        head = fig._suptitle.get_text()
        assert "alpha_l = 1e6" in head and "robustness stage H1" in head  # H1 explained
        assert "mean over the 2 evaluated scenes" in head
    finally:
        plt.close(fig)
    fig = panel_figure(images, torch.rand(2, 1, 16, 16), ["cell", "chelsea"], "H1", table, ("sgan", "sgan_b_gated"))
    try:  # the restorer's column carries its configured name, no other column does
        titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
        assert [t for t in titles if "sgan_b_gated" in t] == ["sgan_b_gated\n(SGAN network)\n20.00 dB"]
    finally:
        plt.close(fig)


def test_joint_comparison_has_row_labels_and_psnr_values():
    from codesign.train.summary import comparison_figure

    learned, published = _images(), _images()
    learned["truth"] = published["truth"] = _images()["input"]
    tables = {"learned": {"sgan": {"psnr": 19.5}, "wiener": {"psnr": 17.0}},
              "published": {"sgan": {"psnr": 19.0}, "wiener": {"psnr": 16.5}}}
    fig = comparison_figure(learned, published, "sgan", "laser_1e6", names=["cell", "chelsea"], tables=tables)
    try:
        assert [ax.get_ylabel() for ax in fig.axes if ax.get_ylabel()] == ["cell", "chelsea"]
        texts = [t.get_text() for ax in fig.axes for t in ax.texts]
        assert len(texts) == 2 * 4 and all(t.endswith(" dB") for t in texts)  # each restoration's PSNR
        assert any("19.50 dB" in ax.get_title() for ax in fig.axes)
    finally:
        plt.close(fig)


def test_tolerance_figure_names_each_sigma_and_the_ceiling_rule():
    from codesign.fab.plate_figures import sigma_text, tolerance_figure

    lsr = {"shift": np.linspace(0.009, 0.011, 8), "all sources": np.linspace(0.009, 0.012, 8)}
    fig = tolerance_figure(lsr, 0.01, 0.012, "t", sigmas={"shift": sigma_text("shift", 1e-5)},
                           ceiling_rule="1.2 x nominal")
    try:
        assert "sigma 10 um" in fig.axes[0].get_title()
        labels = fig.axes[0].get_legend_handles_labels()[1]
        assert any("1.2 x nominal" in label for label in labels)
    finally:
        plt.close(fig)
