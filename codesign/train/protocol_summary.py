"""What the main job (the codesign protocol, codesign/experiments/main_job.py) records, prints and draws: the three
masks, the five systems per laser strength, the gain of each stage with its 95 % interval over the scenes, the goals
of the main job, and one picture of the masks, their PSFs and a scene restored by every system."""
from __future__ import annotations

import math

import numpy as np

from codesign.train.summary import ALPHA_NAMES, paired_difference

METRICS = ("psnr_matched", "psnr", "ssim")
MASKS = ("published", "designed", "co-designed")
TITLES = {"psnr_matched": "PSNR after gain/offset match [dB]", "psnr": "PSNR [dB]", "ssim": "SSIM"}
# system -> (the stage whose evaluation holds it, its column there: the restorer's or the classical Wiener filter's)
SYSTEMS = {"published_wiener": ("published", "wiener"), "published_network": ("published", None),
           "designed_wiener": ("designed", "wiener"), "designed_network": ("designed", None),
           "codesigned_network": ("codesigned", None)}
# stage gains: (label, system, against)
GAINS = (("design stage (designed - published, both + network)", "designed_network", "published_network"),
         ("  of it the optics alone (both + Wiener)", "designed_wiener", "published_wiener"),
         ("joint stage (co-designed - designed + network)", "codesigned_network", "designed_network"),
         ("the network over Wiener (designed mask)", "designed_network", "designed_wiener"),
         ("total (co-designed - published + network)", "codesigned_network", "published_network"))
GOAL_LSR_SHARE = 0.25  # the main job's goals (issue 36): at most a quarter of the published mask's LSR ...
GOAL_DB = {"laser_0": 3.0, "laser_1e3": 1.5, "laser_1e6": 3.0}  # ... and these total gains, beyond the 95 % interval


def _label(system: str, network: str) -> str:
    mask, what = system.rsplit("_", 1)
    mask = {"codesigned": "co-designed"}.get(mask, mask)
    return f"{mask} + {'Wiener' if what == 'wiener' else network}"


def summary_record(metrics: dict, design: dict | None, lsr_max: float, lsr_max_from: str, published_peak: float,
                   seed: int, steps: dict, seconds: dict) -> dict:
    """metrics.json of the main job from the evaluated stages' metrics (``metrics``: published, designed,
    codesigned) and the design stage's (None without one)."""
    pub = metrics["published"]
    method = next(c for c in pub["evaluation"][next(iter(pub["evaluation"]))]
                  if c not in ("sensor", "wiener", "g1_wiener"))
    conds = [c for c in ALPHA_NAMES if c in pub["evaluation"]]
    masks = {}
    for name, stage in zip(MASKS, ("published", "designed", "codesigned")):
        m = metrics[stage]
        masks[name] = {k: m[k] for k in ("lsr", "lsr_sampled", "lsr_smooth", "mtf_mean", "lsr_limit", "lsr_over_limit")
                       if k in m}
        own = m["recheck"]["learned"]  # the stage's mask on a finer pupil grid and a wider window (verify_design)
        masks[name].update(recheck_deviation=own["max_deviation"], recheck_agree=own["agree"])
    systems, per_scene = {}, {}
    for system, (stage, column) in SYSTEMS.items():
        ev, scenes = metrics[stage]["evaluation"], metrics[stage]["evaluation_per_scene_psnr_matched"]
        col = column or method
        systems[system] = {c: {k: ev[c][col][k] for k in METRICS} for c in conds}
        per_scene[system] = {c: scenes[c][col] for c in conds}
    gains = {}
    for label, system, against in GAINS:
        gains[label] = {}
        for c in conds:
            mean, half = paired_difference(per_scene[system][c], per_scene[against][c])
            gains[label][c] = {"mean": mean, "interval": half}
    total = gains[GAINS[-1][0]]
    lsr_ok = masks["co-designed"]["lsr"] <= GOAL_LSR_SHARE * masks["published"]["lsr"]
    goal_rows = {c: total[c]["mean"] >= GOAL_DB[c] and total[c]["interval"] is not None
                 and total[c]["mean"] - total[c]["interval"] > 0 for c in conds if c in GOAL_DB}
    return {"protocol": "codesign", "seed": seed, "network": pub.get("network"), "method": method, **steps,
            "scenes": pub["evaluation_scenes"], "lsr_max": lsr_max, "lsr_max_from": lsr_max_from,
            "lsr_published_peak": published_peak, "masks": masks, "design": _design_facts(design),
            "systems": systems, "per_scene_psnr_matched": per_scene, "gains": gains,
            "goal": {"lsr": lsr_ok, **{f"gain_{c}": ok for c, ok in goal_rows.items()},
                     "met": lsr_ok and len(goal_rows) == len(GOAL_DB) and all(goal_rows.values())},
            "lsr_constraint_met": metrics["codesigned"]["lsr"] <= lsr_max * (1 + 1e-6),
            "seconds": seconds, "minutes": sum(seconds.values()) / 60}


def _design_facts(design: dict | None) -> dict | None:
    if design is None:
        return None
    keys = ("mask_kind", "objective", "algorithm", "evaluations", "feasible", "lsr", "mtf_mean", "lsr_over_limit",
            "restorability", "restorability_published", "window_energy", "seconds")
    return {k: design[k] for k in keys if k in design}


def protocol_summary(r: dict) -> str:
    """The printed end of the main job (its metrics.json, summary_record)."""
    net = r.get("network") or r["method"]
    conds = [c for c in ALPHA_NAMES if c in r["systems"]["published_network"]]
    d = r["design"]
    design = f"design: {d['mask_kind']}, {d['evaluations']} evaluations" if d else "no design stage"
    lines = [f"== main job: seed {r['seed']}, {len(r['scenes'])} held-out test scenes; {design}; restorer "
             f"{r['trainer_steps']} steps, then {r['finetune_steps']} per arm; {r['minutes']:.1f} min ==",
             f"{'mask':<12}{'LSR':>10}{'mtf_mean':>10}{'LSR / limit':>13}  re-check   (LSR: certified laser peak / "
             "unmasked peak, lower protects more; re-check: the largest change of LSR or mtf_mean on a 2x finer "
             "pupil grid and a 2x wider window)"]
    for name in MASKS:  # fixed orders: metrics.json's keys are written sorted
        m = r["masks"][name]
        dev = m.get("recheck_deviation")
        check = "" if dev is None else f"{100 * dev:.2f} % {'ok' if m['recheck_agree'] else 'FAILS'}"
        lines.append(f"{name:<12}{m['lsr']:>10.3e}{m['mtf_mean']:>10.4f}{m['lsr_over_limit']:>13.2f}  {check}")
    share = r["masks"]["co-designed"]["lsr"] / r["masks"]["published"]["lsr"]
    lines.append(f"LSR ceiling {r['lsr_max']:.4g} ({r['lsr_max_from']}); co-designed / published LSR = {share:.3f}")
    head = ", ".join(ALPHA_NAMES[c] for c in conds)
    for metric in METRICS:
        lines.append(f"{TITLES[metric]} at alpha_l = {head}")
        fmt = ".3f" if metric == "ssim" else ".2f"
        for system in SYSTEMS:
            row = r["systems"][system]
            lines.append(f"  {_label(system, net):<38}" + "".join(f"{row[c][metric]:>8{fmt}}" for c in conds))
    lines.append(f"gain of each stage, PSNR matched [dB] at alpha_l = {head} (mean over the scenes +- the 95 % "
                 "interval of the per-scene differences; one seed)")
    for label, _, _ in GAINS:
        row = r["gains"][label]
        cells = []
        for c in conds:
            g = row[c]
            cells.append(f"{g['mean']:+7.2f}" + ("" if g["interval"] is None else f" +-{g['interval']:.2f}"))
        lines.append(f"  {label:<52}" + "  ".join(f"{x:>14}" for x in cells))
    goal = r["goal"]
    parts = [f"LSR <= 1/{1 / GOAL_LSR_SHARE:g} of the published: {'yes' if goal['lsr'] else 'NO'}"]
    parts += [f"total >= +{GOAL_DB[c]:g} dB at {ALPHA_NAMES[c]}: {'yes' if goal[f'gain_{c}'] else 'NO'}"
              for c in conds if f"gain_{c}" in goal]
    lines.append(f"goal ({'met' if goal['met'] else 'NOT met'}): " + "; ".join(parts))
    return "\n".join(lines)


def systems_figure(arrays: dict, images: dict, r: dict):
    """Top: the phase of the published, designed and co-designed masks and their PSFs (log10 of LSR units, so the
    colour reads the laser suppression); bottom: one scene at the compared laser strength: the truth, each mask's
    sensor image and every system's restoration with its PSNR after the gain/offset match (the summary's figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from codesign.train.evaluation import affine_match

    net = r.get("network") or r["method"]
    shown = [("ground truth", "published", "truth"), ("published:\nsensor image", "published", "input"),
             ("published +\nWiener", "published", "wiener"), (f"published +\n{net}", "published", "network"),
             ("designed:\nsensor image", "designed", "input"), ("designed +\nWiener", "designed", "wiener"),
             (f"designed +\n{net}", "designed", "network"), (f"co-designed +\n{net}", "codesigned", "network")]
    fig = plt.figure(figsize=(1.9 * len(shown), 6.6), layout="constrained")
    grid = fig.add_gridspec(2, 2 * len(arrays), height_ratios=(1.25, 1))
    top = grid[0, :].subgridspec(1, 2 * len(arrays))
    for j, (name, a) in enumerate(arrays.items()):
        ax = fig.add_subplot(top[0, 2 * j])
        ax.imshow(np.angle(np.exp(1j * a["phase"])), cmap="twilight", vmin=-np.pi, vmax=np.pi)
        ax.set_title(f"{name} mask: phase", fontsize=8)
        ax.set_axis_off()
        ax = fig.add_subplot(top[0, 2 * j + 1])
        m = a["psf"].shape[0]
        c = slice(m // 4, m - m // 4)  # the central half of the window
        im = ax.imshow(np.log10(np.maximum(a["psf"][c, c], 1e-9)), cmap="magma", vmin=-7, vmax=-2)
        ax.set_title(f"{name}: PSF, log10\n(LSR {r['masks'][name]['lsr']:.3g})", fontsize=8)
        ax.set_axis_off()
    fig.colorbar(im, ax=fig.axes[-1], fraction=0.05, label="log10 (PSF / unmasked peak)")
    bottom = grid[1, :].subgridspec(1, len(shown))
    truth = images["published"]["truth"][:1]
    for j, (title, stage, key) in enumerate(shown):
        img = images[stage][key][:1]
        ax = fig.add_subplot(bottom[0, j])
        vmax = max(float(np.percentile(img.numpy(), 99.5)), 1e-6) if key == "input" else 1.0
        ax.imshow(img[0, 0].numpy(), cmap="gray", vmin=0, vmax=vmax)
        ax.set_axis_off()
        if key != "truth":
            mse = float((affine_match(img.float(), truth.float()) - truth).square().mean())
            title += f"\n{-10 * math.log10(max(mse, 1e-12)):.2f} dB"
        ax.set_title(title, fontsize=8)
    fig.suptitle(f"main job: the published, designed and co-designed cameras; bottom: {r['scenes'][0]} at alpha_l = "
                 "1e6 (this scene's PSNR after the gain/offset match)", fontsize=9)
    return fig
