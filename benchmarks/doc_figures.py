"""The figures the README and docs/ quote, checked against the results files they come from.

    python -m benchmarks.doc_figures            # every quote; exit 1 and a line per mismatch when any differs

Each Quote names a page, the results file a figure comes from, and how the page writes it: ``values`` reads the
file and returns the figures as the page prints them, ``text`` places them (``{}`` each). The page must contain the
text exactly. A rerun that changes a results file then fails the check until the page says the new figure, and a
figure edited by hand cannot drift from its source. tests/test_doc_figures.py runs it in the default test run.
Results files are read under today's metrics names (codesign.io.metric_names).
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from codesign.io.metric_names import read_metrics
from codesign.train.protocol_summary import GAINS

REPO = Path(__file__).resolve().parent.parent
DESIGN = "benchmarks/results/full/design"
PEAKS = f"{DESIGN}/continuous_lsr.json"
WRAPPING = f"{DESIGN}/wrapping_spline_visible.json"
STUDY = "benchmarks/results/codesign_study/study.json"
GATED = "benchmarks/results/early_steps/unitdc_gate_g2gate_ema0.99{}.json"
MAIN_JOB = "benchmarks/results/main_job/metrics.json"
MAIN_JOB_SEED1 = "benchmarks/results/main_job/before_level_head/seed1/metrics.json"
MAIN_JOB_GATED = "benchmarks/results/main_job/gated_recipe/metrics.json"
MAIN_JOB_L1_FIRST = "benchmarks/results/main_job/l1_first_weights/metrics.json"
MAIN_JOB_220 = "benchmarks/results/main_job/steps220_filled/metrics.json"
MAIN_JOB_240 = "benchmarks/results/main_job/steps240/{}/metrics.json"
MAIN_JOB_L1B = "benchmarks/results/main_job/pool_l1b/metrics.json"
MAIN_JOB_NAF = "benchmarks/results/main_job/wiener_naf/seed{}/metrics.json"  # the current default (model=wiener_naf)
GRADIENT = "benchmarks/results/mask_gradient/published_seed{}.json"
PRETRAINED = "benchmarks/results/pretrained/eval_{}.json"
RESTORERS = "benchmarks/results/restorers/restorer_table.json"
TARGET_LEVEL = "benchmarks/results/restorers/target_level/target_level.json"
ADAPTED = "benchmarks/results/pretrained/adapted/{}.json"
JOINT_STAGE = next(label for label, *_ in GAINS if label.startswith("joint stage"))  # the main job's summary row


TARGET_LEVEL_ROWS = (
    "the main job's recipe (gated, scene target, linear alpha_l), seed 0",
    "the main job's recipe, seed 1",
    "ungated G2, log alpha_l, seed 0",
    "ungated, exposure target, log alpha_l, seed 0",
    "ungated, exposure target, log alpha_l, seed 1",
    "the same, L1 only (adv = mdf = 0), seed 0",
    "the same, L1 only, seed 1",
    "the same, L1 only, 800 steps, seed 0",
    "the same, L1 only, learning rates x3 (6e-4 / 1.2e-3), seed 0",
    "the same, L1 only, 3,200 steps, seed 0",
)


def sci(v: float, digits: int = 3) -> str:
    """9.12e-4 (``digits`` significant digits, the exponent without padding), as the pages write LSRs."""
    mantissa, exponent = f"{v:.{digits - 1}e}".split("e")
    return f"{mantissa}e{int(exponent)}"


def fixed(v: float, decimals: int = 2) -> str:
    return f"{v:.{decimals}f}"


def signed(v: float, decimals: int = 2) -> str:
    return f"{v:+.{decimals}f}"


def pct(v: float, decimals: int = 1) -> str:
    """0.204 -> 20.4 %."""
    return f"{100 * v:.{decimals}f} %"


def _padding_row(filled: dict, key: str) -> tuple[str, ...]:
    """One system's PSNR matched at alpha_l = 0 / 1e3 / 1e6 in the 220-step main job on the filled padding, then
    in the same run with model.g2_base_pad=replicate (benchmarks/results/main_job/steps220_replicate/)."""
    replicate = read_metrics(REPO / "benchmarks/results/main_job/steps220_replicate/metrics.json")
    return tuple(fixed(m["systems"][key][f"laser_{a}"]["psnr_matched"]) for m in (filled, replicate)
                 for a in ("0", "1e3", "1e6"))


def _seeds_text(res: dict, start: str = "| seed") -> str:
    """The rendering stored in a seeds.json (by the retired main_job_seeds study, docs/results_log.md), from
    ``start`` (its table, or its verdicts) on."""
    text = res["markdown"]
    return text[text.index(start):].rstrip("\n")


@dataclass(frozen=True)
class Quote:
    page: str
    text: str
    source: str
    values: Callable[[dict], tuple]

    def expected(self) -> str:
        return self.text.format(*self.values(read_metrics(REPO / self.source)))


def _peak(name: str, key: str) -> Callable[[dict], float]:
    return lambda d: d["designs"][name][key]


def _whole_window(d: dict) -> tuple:
    """The spline searched on a window that holds its whole PSF, against the published mask on that window."""
    lsr = _peak("spline_whole_window", "lsr_whole")(d)
    published = read_metrics(REPO / DESIGN / "spline_whole_window" / "metrics.json")["lsr_published"]
    return sci(lsr), f"{published / lsr:.1f}", sci(published), fixed(_peak("spline_whole_window",
                                                                          "lsr_whole_over_limit")(d))


def _wrapping_row(label: str, surface: str, depth: str, bold: tuple = ()) -> Quote:
    """A row of docs/codesign.md's wrapping table: depth, the five lines, worst visible, yield, p95."""
    def values(d):
        s = d["surfaces"][surface]
        lines = [sci(s[line]["lsr"], 3) if s[line]["lsr"] < 0.1 else f"{s[line]['lsr']:.3g}"
                 for line in ("405", "450", "532", "633", "1064")]
        cells = {"worst": sci(s["worst_visible"], 3), "yield": pct(s["tolerance"]["yield"]),
                 "p95": sci(s["tolerance"]["lsr_p95"], 3)}
        cells = {k: f"**{v}**" if k in bold else v for k, v in cells.items()}
        return (depth.format(s["depth_m"] * 1e6), *lines, cells["worst"], cells["yield"], cells["p95"])
    return Quote("docs/codesign.md", f"| {label} | {{}} um | " + " | ".join(["{}"] * 8) + " |", WRAPPING, values)


def _study(arm: str, key: str) -> Callable[[dict], dict]:
    return lambda d: d["summary"][arm][key]


def _gated_row(seed: str, suffix: str) -> Quote:
    def values(d):
        at = d["steps"]["160"]
        return tuple(fixed(at[c]["sgan"]) for c in ("laser_0", "laser_1e3", "laser_1e5", "laser_1e6"))
    return Quote("docs/models.md", f"| {seed} | **network** | **{{}}** | **{{}}** | **{{}}** | **{{}}** |",
                 GATED.format(suffix), values)


def _matched(rows: dict, plus_minus: str = "+-") -> list[str]:
    """The network's matched PSNR (its gain over Wiener) per alpha_l, from an evaluation's per-alpha_l rows
    (benchmarks/pretrained_eval.py's ``alpha``): 25.10 (+1.20 +- 0.40)."""
    return [f"{fixed(rows[a]['sgan']['psnr_matched'])} ({signed(rows[a]['gain_over_wiener']['mean'])} {plus_minus} "
            f"{fixed(rows[a]['gain_over_wiener']['interval'])})" for a in ("0", "1e3", "1e5", "1e6")]


def _pool_row(label: str, run: str) -> Quote:
    """A row of docs/models.md Sec. 11: a network through the held-out mask, matched PSNR (gain over Wiener)."""
    return Quote("docs/models.md", f"| {label} | " + " | ".join(["{}"] * 4) + " |", PRETRAINED.format(run),
                 lambda d: tuple(_matched(d["masks"]["heldout"]["alpha"], "±")))


def _row_cells(rows: dict) -> tuple:
    """_matched, then plain PSNR / SSIM at alpha_l = 0 and 1e6."""
    gains = _matched(rows)
    plain = [f"{fixed(rows[a]['sgan']['psnr'])} / {fixed(rows[a]['sgan']['ssim'], 3)}" for a in ("0", "1e6")]
    return (*gains, *plain)


def _restorer_row(name: str, source: str = RESTORERS) -> Quote:
    """A row of docs/models.md Sec. 8 (or of Sec. 13: ``source`` TARGET_LEVEL) after its step time."""
    return Quote("docs/models.md", " " + " | ".join(["{}"] * 6) + " |", source,
                 lambda d: _row_cells(d["rows"][name]["eval"]["alpha"]))


def _adapted_row(label: str, seed: int, run: str) -> Quote:
    """A row of docs/models.md Sec. 14: a restorer_table run (``adapt...``) or a pretrained_eval of one checkpoint
    on one mask (the main job's arms)."""
    def values(d):
        rows = d["rows"]["sgan_b_l1"]["eval"]["alpha"] if "rows" in d else next(iter(d["masks"].values()))["alpha"]
        return _row_cells(rows)
    return Quote("docs/models.md", f"| {label} | {seed} | " + " | ".join(["{}"] * 6) + " |", ADAPTED.format(run),
                 values)


def _gain_cells(m: dict, label: str) -> tuple[str, ...]:
    """One of the main job's gain rows per alpha_l as the page writes it: +4.20 +- 1.45."""
    row = m["gains"][label]
    return tuple(f"{signed(row[c]['mean'])} +- {fixed(row[c]['interval'])}"
                 for c in ("laser_0", "laser_1e3", "laser_1e6"))


def _total_gains(m: dict) -> tuple[str, ...]:
    """The main job's total gain per alpha_l (its last gain row)."""
    return _gain_cells(m, GAINS[-1][0])


def _seed_row(m: dict) -> tuple[str, ...]:
    """A seed's row of the main job's seed table: the total gain per alpha_l, then the joint stage's at 1e6."""
    joint = m["gains"][JOINT_STAGE]["laser_1e6"]
    return (*_total_gains(m), f"{signed(joint['mean'])} +- {fixed(joint['interval'])}")


def _naf_seed_row(m: dict) -> tuple[str, ...]:
    """A seed's row of the current main job's table: minutes, the co-designed / published LSR, then the total, the
    joint stage and the network over Wiener on the designed mask per alpha_l."""
    labels = [label for label, *_ in GAINS]
    over_wiener = next(label for label in labels if label.startswith("the network over Wiener"))
    return (fixed(m["minutes"], 1), fixed(m["masks"]["co-designed"]["lsr"] / m["lsr_published_peak"], 3),
            *_total_gains(m), *_gain_cells(m, JOINT_STAGE), *_gain_cells(m, over_wiener))


def _main_job_summary(m: dict) -> tuple[str]:
    """The printed end of the main job's run, rebuilt from its metrics.json exactly as the run prints it."""
    from codesign.train.protocol_summary import protocol_summary

    return (protocol_summary(m),)


QUOTES: list[Quote] = [
    # README's headline: the designs against the limit (certified continuous peaks)
    Quote("README.md", "**LSR {}**, {}x below the published mask's {} and {}x the physical limit", PEAKS,
          lambda d: _whole_window(d)),
    Quote("README.md", "four starts reach LSR {}, {}x the", PEAKS,
          lambda d: (sci(_peak("spline_multistart", "lsr_whole")(d)),
                     fixed(_peak("spline_multistart", "lsr_whole_over_limit")(d)))),
    Quote("README.md", "holds **LSR <= {} at each of them**", WRAPPING,
          lambda d: (sci(d["surfaces"]["smooth"]["worst_visible"]),)),
    Quote("docs/codesign.md", "{}, {}x the limit**", PEAKS,
          lambda d: (sci(_peak("spline_multistart", "lsr_whole")(d), 4),
                     fixed(_peak("spline_multistart", "lsr_whole_over_limit")(d)))),
    # docs/codesign.md Sec. 5: wrapping as a design choice
    _wrapping_row("continuous surface", "smooth", "{:.2f}", bold=("worst", "p95")),
    _wrapping_row("2 pi-wrapped plate", "wrapped", "{:.3f}", bold=("yield",)),
    _wrapping_row("2-wave plate", "2-wave", "{:.2f}"),
    _wrapping_row("4-wave plate", "4-wave", "{:.2f}"),
    # docs/codesign.md Sec. 7: the study's headline gains (study.json's summary)
    Quote("docs/codesign.md", "**+{} dB** at alpha_l = 1e6 ({} +- {} against {} +- {}; paired gains +{} +- {}", STUDY,
          lambda d: (fixed(_study("spline (frozen)", "net_psnr_matched_1e6")(d)["gain"]),
                     fixed(_study("spline (frozen)", "net_psnr_matched_1e6")(d)["mean"]),
                     fixed(_study("spline (frozen)", "net_psnr_matched_1e6")(d)["std"]),
                     fixed(_study("published (frozen)", "net_psnr_matched_1e6")(d)["mean"]),
                     fixed(_study("published (frozen)", "net_psnr_matched_1e6")(d)["std"]),
                     fixed(_study("spline (frozen)", "net_psnr_matched_1e6")(d)["gain"]),
                     fixed(_study("spline (frozen)", "net_psnr_matched_1e6")(d)["gain_std"]))),
    Quote("docs/codesign.md", "Spiral (3 parameters): LSR {} (5x below), +{} +- {} dB at 1e6", STUDY,
          lambda d: (sci(_study("spiral (frozen)", "lsr")(d)["mean"]),
                     fixed(_study("spiral (frozen)", "net_psnr_matched_1e6")(d)["gain"]),
                     fixed(_study("spiral (frozen)", "net_psnr_matched_1e6")(d)["gain_std"]))),
    Quote("docs/codesign.md", "(-{} +- {} dB)", STUDY,
          lambda d: (fixed(-_study("joint from published", "net_psnr_matched_1e6")(d)["gain"]),
                     fixed(_study("joint from published", "net_psnr_matched_1e6")(d)["gain_std"]))),
    # docs/models.md Sec. 10: the main job's network at the CPU budget, two seeds
    _gated_row("0", ""),
    _gated_row("1", "_seed1"),
    # docs/models.md Sec. 11: the shipped pool restorer and a one-mask network through the held-out mask
    _pool_row("pool of 12 masks (shipped until the L1 weights)", "pool_seed0"),
    _pool_row("pool of 12 masks, L1 recipe, 6,400 + 2,400 steps (shipped until the second pool run)", "pool_l1"),
    _pool_row("pool of 12 masks, L1 recipe, 6,400 + 2,400 + 2,400 steps (shipped until the third pool run)",
              "pool_l1b"),
    _pool_row("pool of 12 masks, L1 recipe, 6,400 + 3 x 2,400 steps, the last with the replicated padding (shipped)",
              "pool_l1c"),
    _pool_row("this mask alone", "single_heldout"),
    _pool_row("pool of 10 spline masks, no half rings", "spline_pool"),
    _pool_row("pool of 12 masks, G1 with the halo channel", "pool_halo"),
    _pool_row("this mask alone, G1 with the halo channel", "single_halo"),
    _pool_row("pool of 12 masks, 1,600 steps", "pool_1600"),
    # docs/models.md Sec. 8: every restorer at 400 steps on the published mask
    *(_restorer_row(n) for n in ("sgan_b", "sgan_e", "sgan_f", "sgan_b_gated", "wiener_unet")),
    _restorer_row("wiener_naf", "benchmarks/results/restorers/wiener_naf/restorer_table.json"),
    _restorer_row("shipped (pool, own budget)", "benchmarks/results/restorers/wiener_naf/restorer_table.json"),
    *(_restorer_row(n, TARGET_LEVEL) for n in TARGET_LEVEL_ROWS),
    *(Quote("docs/models.md", f"| {label} | n/a | n/a | " + " | ".join(["{}"] * 6) + " |", PRETRAINED.format(run),
            lambda d: _row_cells(d["masks"]["published"]["alpha"]))
      for label, run in (("shipped until the second pool run (L1 recipe, 6,400 + 2,400 pool steps)", "pool_l1"),
                         ("shipped until the third pool run (L1 recipe, 6,400 + 2,400 + 2,400 pool steps)",
                          "pool_l1b"),
                         ("shipped (L1 recipe, 6,400 + 2,400 + 2,400 + 2,400 pool steps, the last with the "
                          "replicated padding)", "pool_l1c"))),
    # docs/models.md Sec. 14: the shipped network adapted to a mask
    *(_adapted_row(label, seed, run) for label, seed, run in (
        ("adapted, 320 steps", 0, "adapt_published_s0"), ("adapted, 320 steps", 1, "adapt_published_s1"),
        ("adapted, 960 steps", 0, "adapt960_published_s0"),
        ("the main job's published arm (200 + 120 steps)", 0, "published_s0"),
        ("the main job's published arm", 1, "published_s1"), ("the main job's published arm", 2, "published_s2"),
        ("adapted, 320 steps", 0, "adapt_spline_s0"), ("adapted, 320 steps", 1, "adapt_spline_s1"),
        ("adapted, 960 steps", 0, "adapt960_spline_s0"), ("adapted, 960 steps", 1, "adapt960_spline_s1"),
        ("the main job's designed arm (200 + 120 steps)", 0, "designed_s0"),
        ("the main job's designed arm", 1, "designed_s1"), ("the main job's designed arm", 2, "designed_s2"))),
    # docs/models.md Sec. 13: the base's padding, the 220-step main job filled against replicate
    *(Quote("docs/models.md", f"| {label} + network | {{}} / {{}} / {{}} | {{}} / {{}} / {{}} |", MAIN_JOB_220,
            lambda m, key=key: _padding_row(m, key)) for label, key in
      (("published", "published_network"), ("designed", "designed_network"), ("co-designed", "codesigned_network"))),
    # docs/codesign.md Sec. 7: the mask gradient's signal against its noise, two seeds
    Quote("docs/codesign.md", "is **{}** (seed 0) and **{}** (seed 1)", GRADIENT.format(0),
          lambda d: (fixed(d["snr_one_batch"]), fixed(read_metrics(REPO / GRADIENT.format(1))["snr_one_batch"]))),
    # docs/codesign.md Sec. 7: the current main job's summary as its run printed it (main_job/wiener_naf/seed0/)
    Quote("docs/codesign.md", "{}", MAIN_JOB_NAF.format(0), _main_job_summary),
    *(Quote("docs/codesign.md", f"| {k} | " + " | ".join(["{}"] * 11) + " |", MAIN_JOB_NAF.format(k), _naf_seed_row)
      for k in (0, 1, 2)),
    # docs/results_log.md: the previous default's (benchmarks/results/main_job/)
    Quote("docs/results_log.md", "{}", MAIN_JOB, _main_job_summary),
    # ... the three seeds at 240 restorer steps and the mixed laser strengths (benchmarks/results/main_job/steps240/)
    *(Quote("docs/codesign.md", " | {} | {} | {} | {} |", MAIN_JOB_240.format(run), _seed_row)
      for run in ("seed0", "seed1", "seed2", "mixed_lasers")),
    # ... and the moonshot at an eighth of the published LSR (benchmarks/results/main_job/eighth/)
    *(Quote("docs/codesign.md", f"| published/8, seed {k} | {{}} | {{}} | {{}} | {{}} |",
            f"benchmarks/results/main_job/eighth/{sub}metrics.json", _seed_row)
      for k, sub in ((0, ""), (1, "seed1/"), (2, "seed2/"))),
    # ... and the joint stage over the seeds (seeds.json): the moonshot's table, the quarter's verdict
    Quote("docs/codesign.md", "{}", "benchmarks/results/main_job/eighth/seeds.json", lambda d: (_seeds_text(d),)),
    Quote("docs/codesign.md", "{}", "benchmarks/results/main_job/steps240/seeds.json",
          lambda d: (_seeds_text(d, "- main-job goal"),)),
    Quote("docs/results_log.md", "{}", "benchmarks/results/main_job/seeds.json", lambda d: (_seeds_text(d),)),
    # ... and the quarter with twice the arms' steps (benchmarks/results/main_job/quarter_ft240/)
    Quote("docs/codesign.md", "| 240 | {} | {} | {} +- {} | {} |",
          "benchmarks/results/main_job/quarter_ft240/metrics.json",
          lambda m: (fixed(m["systems"]["designed_network"]["laser_1e6"]["psnr_matched"]),
                     fixed(m["systems"]["codesigned_network"]["laser_1e6"]["psnr_matched"]),
                     signed(m["gains"][JOINT_STAGE]["laser_1e6"]["mean"]),
                     fixed(m["gains"][JOINT_STAGE]["laser_1e6"]["interval"]),
                     fixed(m["masks"]["co-designed"]["lsr"] / m["lsr_published_peak"], 3))),
    # ... its headline gains
    Quote("docs/results_log.md", "restores {} dB better at alpha_l = 0,\n{} at 1e3 and {} at 1e6", MAIN_JOB,
          lambda m: _total_gains(m)),
    # docs/results_log.md: the main job's runs with the gated recipe (benchmarks/results/main_job/gated_recipe/,
    # before_level_head/seed1/)
    Quote("docs/results_log.md", "{}", MAIN_JOB_GATED, _main_job_summary),
    # ... at 220 restorer steps with the filled base padding (benchmarks/results/main_job/steps220_filled/)
    Quote("docs/results_log.md", "{}", MAIN_JOB_220, _main_job_summary),
    Quote("docs/results_log.md", "restores {} dB better at alpha_l = 0,\n{} at 1e3 and {} at 1e6", MAIN_JOB_220,
          lambda m: _total_gains(m)),
    # ... and with the first L1 pool weights (benchmarks/results/main_job/l1_first_weights/)
    Quote("docs/results_log.md", "{}", MAIN_JOB_L1_FIRST, _main_job_summary),
    Quote("docs/results_log.md", "total gain {} dB at alpha_l = 0,\n  {} at 1e3, {} at 1e6", MAIN_JOB_SEED1,
          lambda m: _total_gains(m)),
    # ... and with the second pool run's weights, its seeds (benchmarks/results/main_job/pool_l1b/)
    Quote("docs/results_log.md", "{}", MAIN_JOB_L1B, _main_job_summary),
    Quote("docs/results_log.md", "restores {} dB better at alpha_l = 0,\n{} at 1e3 and {} at 1e6", MAIN_JOB_L1B,
          lambda m: _total_gains(m)),
    Quote("docs/results_log.md", "{}", "benchmarks/results/main_job/pool_l1b/seeds.json", lambda d: (_seeds_text(d),)),
]


def check(quotes: list[Quote] | None = None) -> list[str]:
    """One line per quote whose page does not contain its figures as the results file has them."""
    problems = []
    for q in QUOTES if quotes is None else quotes:
        try:
            want = q.expected()
        except (OSError, KeyError, ValueError) as e:
            problems.append(f"{q.page}: cannot read the figures of {q.text!r} from {q.source}: {e!r}")
            continue
        if want not in (REPO / q.page).read_text():
            problems.append(f"{q.page}: does not say {want!r} (from {q.source})")
    return problems


def main() -> int:
    problems = check()
    for p in problems:
        print(p)
    print(f"{len(QUOTES) - len(problems)} of {len(QUOTES)} quoted figures agree with their results files")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
