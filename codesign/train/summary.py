"""What a joint run prints at its end and draws for a newcomer: the two masks, the two restorations with the sensor
image and classical Wiener as floors, a verdict that says when a difference is within noise, and the two systems'
restorations side by side."""
from __future__ import annotations

import math
import statistics

import numpy as np

ALPHA_NAMES = {"laser_0": "0", "laser_1e3": "1e3", "laser_1e6": "1e6"}
VERDICT_CONDITION = "laser_1e6"


def paired_difference(learned: list[float], published: list[float]) -> tuple[float, float | None]:
    """Mean of the per-scene differences and the half-width of its 95 % confidence interval (Student's t with n - 1
    degrees of freedom: with 2 scenes the factor is 12.7, not 2); None below 2 scenes: no noise estimate."""
    from scipy.stats import t

    d = [a - b for a, b in zip(learned, published)]
    if len(d) < 2:
        return statistics.mean(d), None
    return statistics.mean(d), float(t.ppf(0.975, len(d) - 1)) * statistics.stdev(d) / math.sqrt(len(d))


def restorer_scores(evaluation: dict, method: str, suffix: str = "") -> dict:
    """psnr / ssim (plain, and _matched: after the gain/offset match) of the restorer's restorations (column
    ``method``), the mean over the conditions and per condition, keys ending in ``suffix`` ("_published": the
    published system's)."""
    out = {}
    for metric in ("psnr", "ssim", "psnr_matched", "ssim_matched"):
        vals = {cond: t[method][metric] for cond, t in evaluation.items()}
        out[f"{metric}{suffix}"] = float(np.mean(list(vals.values())))
        for cond, v in vals.items():
            out[f"{metric}{suffix}_{cond}"] = v
    return out


def verdict(m: dict, method: str, condition: str = VERDICT_CONDITION) -> str:
    """One line: the learned system's PSNR (after the gain/offset match) against the published one at
    ``condition``, and whether the difference is outside the 95 % interval of the per-scene differences. One run
    is one seed: the seed-to-seed spread is not in it (runs of other ``seed=`` values measure it)."""
    learned = m["evaluation_per_scene_psnr_matched"][condition][method]
    published = m["evaluation_per_scene_psnr_matched_published"][condition][method]
    mean, noise = paired_difference(learned, published)
    lsr_change = m["lsr"] / m["lsr_published"] - 1
    alpha = ALPHA_NAMES.get(condition, condition)
    head = (f"verdict: the learned mask lets {abs(lsr_change):.0%} {'less' if lsr_change < 0 else 'more'} laser "
            f"light through; at alpha_l = {alpha} its restoration is {mean:+.2f} dB against the published system's")
    if noise is None:
        return head + f" ({len(learned)} scene: no noise estimate; evaluate more scenes to judge)"
    judged = "beyond the scene noise (one seed: runs with other seed= values measure the seed spread)" \
        if abs(mean) > noise else "within noise"
    return head + f" ({len(learned)} scenes; 95 % interval of the per-scene differences +-{noise:.2f} dB): {judged}"


def joint_summary(m: dict, method: str) -> str:
    """The printed end of a joint run with its published comparison (metrics.json's keys)."""
    scenes = len(m["evaluation_scenes"])
    lines = [f"== summary: {m['steps']} steps, seed {m.get('seed', 0)}, {scenes} held-out test scene(s) ==",
             f"{'mask':<11}{'LSR':>10}{'mtf_mean':>10}{'LSR / limit':>13}   (LSR: laser peak / unmasked peak; "
             "lower protects more)"]
    for name, sfx in (("learned", ""), ("published", "_published")):
        lines.append(f"{name:<11}{m['lsr' + sfx]:>10.3e}{m['mtf_mean' + sfx]:>10.4f}{m['lsr_over_limit' + sfx]:>13.2f}")
    if "recheck_gain_moved" in m:
        r = m["recheck"]
        lines.append(f"re-check on a {r['learned']['fine_factor']}x finer pupil grid and a 2x wider window: LSR "
                     f"learned / published {r['lsr_ratio_design']:.3f} -> {r['lsr_ratio_fine']:.3f} (fine), "
                     f"{r['lsr_ratio_whole']:.3f} (wide); the gain moves by {100 * m['recheck_gain_moved']:.1f} % "
                     f"({'ok' if m['recheck_agree'] else 'more than 2 %: partly the simulation, not the optics'})")
    conds = [c for c in ALPHA_NAMES if c in m["evaluation"]]
    lines.append("PSNR after gain/offset match [dB] at alpha_l = " + ", ".join(ALPHA_NAMES[c] for c in conds))
    net = m.get("network", "network")  # the network's name as configured (model.name)
    rows = ((f"learned mask + {net}", "evaluation", method), (f"published mask + {net}", "evaluation_published",
            method), ("  floor: sensor image (published)", "evaluation_published", "sensor"),
            ("  floor: classical Wiener (published)", "evaluation_published", "wiener"))
    for label, key, col in rows:
        lines.append(f"{label:<40}" + "".join(f"{m[key][c][col]['psnr_matched']:>8.2f}" for c in conds))
    if VERDICT_CONDITION in conds:
        lines.append(verdict(m, method))
    return "\n".join(lines)


def comparison_figure(learned: dict, published: dict, method: str, condition: str, rows: int = 3,
                      names: list[str] | None = None, tables: dict | None = None, network: str | None = None):
    """Both systems side by side at one condition: truth, then per mask its sensor image, Wiener and the network
    (``learned`` / ``published``: evaluation images, run_evaluation(keep=...)); a row per scene (``names``: their
    names), each panel with its PSNR against the truth [dB], each column's title with the mean over every
    evaluated scene when ``tables`` ({"learned": table, "published": table}, the condition's evaluation tables);
    ``network``: the restorer's name as configured."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from codesign.train.evaluation import method_title

    cols = [("ground truth", learned, "truth", None), ("published mask:\nsensor image", published, "input", None),
            ("published mask:\nclassical Wiener", published, "wiener", "published"),
            (f"published mask:\n{method_title(method, network)}", published, method, "published"),
            ("learned mask:\nsensor image", learned, "input", None),
            ("learned mask:\nclassical Wiener", learned, "wiener", "learned"),
            (f"learned mask:\n{method_title(method, network)}", learned, method, "learned")]
    n = min(rows, learned["truth"].shape[0])
    fig, axes = plt.subplots(n, len(cols), figsize=(2.0 * len(cols), 2.1 * n + 0.9), squeeze=False)
    for i in range(n):
        truth = learned["truth"][i, 0].numpy()
        for j, (title, images, key, system) in enumerate(cols):
            img = images[key][i, 0].numpy()
            vmax = max(float(np.percentile(img, 99.5)), 1e-6) if key == "input" else 1.0
            ax = axes[i][j]
            ax.imshow(img, cmap="gray", vmin=0, vmax=vmax)
            ax.set_xticks([])
            ax.set_yticks([])
            if key not in ("truth", "input"):  # this scene's PSNR of the shown restoration
                mse = float(np.mean((np.clip(img, 0, 1) - truth) ** 2))
                ax.text(0.03, 0.04, f"{-10 * math.log10(max(mse, 1e-12)):.2f} dB", transform=ax.transAxes,
                        fontsize=7, color="yellow", bbox={"facecolor": "black", "alpha": 0.6, "pad": 1.5,
                                                          "lw": 0})
            if i == 0:
                table = (tables or {}).get(system) if system else None
                if table and key in table:
                    title += f"\nmean {table[key]['psnr']:.2f} dB"
                ax.set_title(title, fontsize=7)
            if j == 0:
                ax.set_ylabel(names[i] if names and i < len(names) else f"scene {i + 1}", fontsize=8)
    scenes = learned["truth"].shape[0]
    fig.suptitle(f"published vs learned mask at laser strength alpha_l = {ALPHA_NAMES.get(condition, condition)}; "
                 f"in each panel: that scene's PSNR [dB];\ncolumn titles: the mean PSNR over the {scenes} evaluated "
                 f"scene{'s' * (scenes != 1)}", fontsize=9)
    fig.tight_layout()
    return fig
