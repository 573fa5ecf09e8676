"""Peers: the identical pupil field propagated by codesign and by hcipy, prysm and poppy, side by side.

The field is the published half-ring mask's A exp(i phi) (computed once by codesign in float64), propagated onto
the 640 x 640 window at the 5.4 um sensor pitch, lambda f of Table 1, at 384 and 1024 samples across the aperture,
float32 and float64, 1 and 2 threads. Each thread count runs in its own process (``worker``), whose BLAS / OpenMP
thread pools are set in its environment before Python starts (numpy's OpenBLAS reads them once, when it loads, and
``benchmarks.common`` loads torch and with it numpy: set later, a 1-thread cell ran prysm's and poppy's matrix
products on 2 threads); inside it the libraries take turns on the same field, in blocks of a few
calls (one call at a time let the previous library's spinning BLAS threads slow the next: codesign's chirp-z
measured 69 ms instead of 14), three rounds, the median of every timed call. Each library's intensity is
normalized by its own propagation of the aperture alone (the uncoded peak), so the sampled LSR and the PSF compare
directly with codesign's.

Peers (optional: ``pip install -e ".[peers]"``; a peer that does not import is skipped with a line saying so):
  hcipy   FraunhoferPropagator onto the window (its own choice of transform: MFT, FFT or zoom FFT)
  prysm   focus_fixed_sampling, method mdft (matrix DFT) and czt (chirp-z)
  poppy   matrix_dft (MatrixFourierTransform), float64 only (it computes in float64 whatever it is given)

codesign: ``propagator: auto`` (docs/optics.md), and the MFT for reference. Its forward + backward (the smooth LSR
differentiated to the phase) is compared with what a gradient costs a peer without autograd: finite differences
over the 10 half-ring parameters, 11 forward propagations (a lower bound: the phase evaluations not counted).

    python -m benchmarks --only peers [--scale full]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
import types
from pathlib import Path

from benchmarks.common import Report, markdown_table, run_isolated, write_json

SAMPLES = {"quick": [384, 1024], "full": [384, 1024]}
REPEATS = {"quick": 3, "full": 5}  # per block; ROUNDS blocks per library
ROUNDS = 3
THREADS = (1, 2)
DTYPES = ("float32", "float64")
FOCAL_N = 640
PEERS = ("hcipy", "prysm", "poppy")
# Seconds of rest before each library's block: thread pools spin a while after their last call (OpenMP, OpenBLAS)
# and, on 2 cores, slow whichever library runs next (codesign's chirp-z at 384 samples, 2 threads, float64: 25-31 ms
# right after the peers' blocks, 12 ms alone; OpenBLAS's threads spin ~0.1 s by default).
SETTLE_S = 0.2
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def _import_peer(name: str):
    """The peer module, or None when it does not import. prysm 0.21.1 reads its version through pkg_resources,
    which setuptools >= 81 no longer ships: a one-line stand-in from importlib.metadata is put in its place."""
    if name == "prysm" and "pkg_resources" not in sys.modules:
        try:
            import pkg_resources  # noqa: F401
        except ImportError:
            import importlib.metadata as md

            stub = types.ModuleType("pkg_resources")
            stub.get_distribution = lambda dist: types.SimpleNamespace(version=md.version(dist))
            sys.modules["pkg_resources"] = stub
    try:
        module = __import__(name)
        if name == "prysm":
            from prysm import propagation  # noqa: F401
        if name == "poppy":
            from poppy import matrixDFT  # noqa: F401
        return module
    except Exception:  # any import failure means: not available here
        return None


def _propagators(spec, dtype_name: str) -> dict:
    """name -> (fn(field) -> intensity ndarray / tensor, input field builder) for every available library."""
    import numpy as np
    import torch

    from codesign.optics.propagation import Propagator

    n, m = spec.grid_n, spec.focal_n
    cdt = np.complex64 if dtype_name == "float32" else np.complex128
    tdt = torch.float32 if dtype_name == "float32" else torch.float64
    out = {}
    for method in ("auto", "mft"):
        prop = Propagator(spec.replace(propagator=method), dtype=tdt)
        label = f"codesign ({prop.method})" if method == "auto" else "codesign (mft)"
        if method == "mft" and label in out:
            continue
        out[label] = (lambda f, p=prop: p.intensity(f), "torch")
    hcipy = _import_peer("hcipy")
    if hcipy is not None:
        # hcipy runs scipy.fft on every core it finds (hcipy._math.fft._CPU_COUNT), whatever OMP_NUM_THREADS says:
        # held to this cell's thread count, as every other library is
        import hcipy._math.fft as hcipy_fft

        hcipy_fft._CPU_COUNT = torch.get_num_threads()
        pupil = hcipy.make_uniform_grid([n, n], [n * spec.pupil_pitch_m] * 2, has_center=True)
        focal = hcipy.make_uniform_grid([m, m], [m * spec.focal_pitch_m] * 2, has_center=True)
        prop = hcipy.FraunhoferPropagator(pupil, focal, focal_length=spec.focal_length_m)

        def run_hcipy(f, prop=prop, pupil=pupil):
            wf = hcipy.Wavefront(hcipy.Field(f.ravel(), pupil), spec.wavelength_m)
            return np.asarray(prop.forward(wf).power).reshape(m, m)

        out["hcipy"] = (run_hcipy, "numpy")
    prysm = _import_peer("prysm")
    if prysm is not None:
        from prysm import propagation

        for method in ("mdft", "czt"):
            def run_prysm(f, method=method):
                e = propagation.focus_fixed_sampling(f, spec.pupil_pitch_m * 1e3, spec.focal_length_m * 1e3,
                                                     spec.wavelength_m * 1e6, spec.focal_pitch_m * 1e6, m,
                                                     method=method)
                return np.abs(e) ** 2

            out[f"prysm ({method})"] = (run_prysm, "numpy")
    poppy = _import_peer("poppy")
    if poppy is not None and dtype_name == "float64":
        from poppy.matrixDFT import matrix_dft

        nlamd = m * spec.focal_pitch_m * n * spec.pupil_pitch_m / spec.lambda_f

        def run_poppy(f):
            # poppy's transform has the opposite sign (its PSF is the physical one mirrored through the axis):
            # the conjugate field under its sign gives the physical PSF, at the same cost
            return np.abs(matrix_dft(np.conj(f), nlamd, m, centering="FFTSTYLE")) ** 2

        out["poppy (matrix DFT)"] = (run_poppy, "numpy")
    return {k: (fn, kind, cdt) for k, (fn, kind) in out.items()}


def worker(argv: list[str] | None = None) -> dict:
    """One thread count: ``OMP_NUM_THREADS=T OPENBLAS_NUM_THREADS=T MKL_NUM_THREADS=T NUMEXPR_NUM_THREADS=T
    python -m benchmarks.bench_peers worker --threads T --samples 384,1024 --repeats R`` (measure() sets them);
    prints one JSON line."""
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_peers worker")
    ap.add_argument("--threads", type=int, required=True)
    ap.add_argument("--samples", required=True)
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args(argv)
    wrong = {v: os.environ.get(v) for v in THREAD_VARS if os.environ.get(v) != str(a.threads)}
    if wrong:
        raise SystemExit(f"bench_peers worker --threads {a.threads}: the thread pools must be set before Python "
                         f"starts ({', '.join(f'{k}={v}' for k, v in wrong.items())}); run it through measure()")
    import numpy as np
    import torch

    torch.set_num_threads(a.threads)
    from codesign.optics import OpticalSystem, OpticsSpec, metrics
    from codesign.optics.masks import published_halfring

    versions = {"torch": torch.__version__, "numpy": np.__version__}
    for name in PEERS:
        mod = _import_peer(name)
        versions[name] = getattr(mod, "__version__", "?") if mod is not None else None
    rows = []
    for samples in (int(s) for s in a.samples.split(",")):
        spec = OpticsSpec.with_samples_across(samples, focal_n=FOCAL_N)
        ref = OpticalSystem(spec, dtype=torch.float64)
        phase = published_halfring(ref.grid, spec.aperture_diameter_m).phase().detach()
        fields = {"coded": ref.field(phase), "uncoded": ref.field(torch.zeros_like(phase))}
        for dtype_name in DTYPES:
            props = _propagators(spec, dtype_name)
            inputs = {}
            for label, (fn, kind, cdt) in props.items():
                if kind == "torch":
                    tdt = torch.complex64 if dtype_name == "float32" else torch.complex128
                    inputs[label] = {k: v.to(tdt) for k, v in fields.items()}
                else:
                    inputs[label] = {k: v.numpy().astype(cdt) for k, v in fields.items()}
            results = {label: {} for label in props}
            for label, (fn, _, _) in props.items():  # figures and a warm-up
                with torch.no_grad():
                    coded, uncoded = (np.asarray(torch.as_tensor(fn(inputs[label][k])).double())
                                      for k in ("coded", "uncoded"))
                peak0 = float(uncoded.max())
                results[label]["psf"] = coded / peak0
                results[label]["lsr_sampled"] = float(coded.max()) / peak0
            times = {label: [] for label in props}
            for _ in range(ROUNDS):  # interleaved: the libraries take turns, a block of repeats each
                for label, (fn, _, _) in props.items():
                    time.sleep(SETTLE_S)  # the previous library's idle threads stop spinning first
                    with torch.no_grad():
                        fn(inputs[label]["coded"])  # the block's first call wakes this library's thread pool
                        for _ in range(a.repeats):
                            t0 = time.perf_counter()
                            fn(inputs[label]["coded"])
                            times[label].append(time.perf_counter() - t0)
            system = OpticalSystem(spec, dtype=torch.float32 if dtype_name == "float32" else torch.float64)
            fb = _codesign_forward_backward(system, phase, a.repeats, metrics)
            chain = _codesign_chain(system, a.repeats)
            base = next(label for label in props if label.startswith("codesign ("))
            for label in props:
                diff = np.abs(results[label]["psf"] - results[base]["psf"]).max() / results[base]["psf"].max()
                rows.append({"samples": samples, "grid_n": spec.grid_n, "threads": a.threads, "dtype": dtype_name,
                             "library": label, "forward_s": statistics.median(times[label]),
                             "lsr_sampled": results[label]["lsr_sampled"], "max_rel_psf_diff": float(diff),
                             "codesign_forward_backward_s": fb if label == base else None,
                             "codesign_chain_s": chain if label == base else None})
            print(f"  {samples} across, {a.threads} thread(s), {dtype_name}: " + ", ".join(
                f"{r['library']} {1e3 * r['forward_s']:.1f} ms" for r in rows[-len(props):]), file=sys.stderr,
                flush=True)
    result = {"rows": rows, "versions": versions}
    print(json.dumps(result))
    return result


def _codesign_chain(system, repeats) -> float:
    """Median seconds of the whole differentiable chain, forward + backward: the 10 half-ring parameters -> phase
    (exact Bessel harmonics) -> field -> PSF -> smooth LSR (codesign.design.merit.time_forward_backward)."""
    from codesign.design.merit import time_forward_backward
    from codesign.optics.masks import HalfRingMask

    mask = HalfRingMask(system.grid, system.spec.aperture_diameter_m)
    fwd, bwd = time_forward_backward(system, mask, 16.0, repeats)
    return fwd + bwd


def _codesign_forward_backward(system, phase, repeats, metrics) -> float:
    """Median seconds of phase -> field -> PSF -> smooth LSR and its gradient to the phase (auto propagator)."""
    ph = phase.to(system.dtype)
    runs = []
    for i in range(repeats + 1):
        p = ph.clone().requires_grad_(True)
        t0 = time.perf_counter()
        metrics.lsr_smooth(system.psf(p), system.uncoded_peak, 16.0).backward()
        if i:
            runs.append(time.perf_counter() - t0)
    return statistics.median(runs)


def measure(scale: str) -> dict:
    samples = ",".join(str(s) for s in SAMPLES[scale])
    out = {"threads": {}}
    for t in THREADS:
        print(f"  peers: {t} thread(s), {samples} samples across", flush=True)
        out["threads"][str(t)] = run_isolated("benchmarks.bench_peers",
                                              ["worker", "--threads", str(t), "--samples", samples,
                                               "--repeats", str(REPEATS[scale])],
                                              env={v: str(t) for v in THREAD_VARS})
    return out


def report(data: dict) -> Report:
    rep = Report("peers", "Peers: the same pupil field through codesign, hcipy, prysm and poppy")
    rows = [r for t in data["threads"].values() for r in t["rows"]]
    versions = next(iter(data["threads"].values()))["versions"]
    missing = [p for p in PEERS if versions.get(p) is None]
    rep.notes.append(
        "The published half-ring field A exp(i phi), propagated onto the 640 x 640 window at 5.4 um (forward "
        "intensity only, median of the repeats, libraries interleaved in one process per thread count, a "
        f"{SETTLE_S:g} s rest before each library's block so that the previous one's idle threads have stopped "
        "spinning). Ratio: the "
        "library's time over codesign's (auto propagator) in the same cell; agreement: the largest difference of "
        "the PSF normalized by the library's own uncoded peak, relative to codesign's peak. The last column: "
        "codesign's forward + backward to the phase against a peer's finite-difference gradient over the 10 "
        "half-ring parameters (11 forward propagations, phase evaluations not counted); 'chain': codesign's whole "
        "differentiable chain, forward + backward, from the 10 half-ring parameters (phase by exact Bessel "
        "harmonics, PSF, smooth LSR). Versions: "
        + ", ".join(f"{k} {v}" for k, v in versions.items() if v) + "."
        + (f" Not installed, skipped: {', '.join(missing)} (pip install -e \".[peers]\")." if missing else "")
        + " hcipy's FFTs are held to the cell's thread count (it uses every core otherwise).")
    cells = sorted({(r["samples"], r["threads"], r["dtype"]) for r in rows})
    won = []
    for cell in cells:
        here = [r for r in rows if (r["samples"], r["threads"], r["dtype"]) == cell]
        best = min(here, key=lambda r: r["forward_s"])
        won.append(best["library"].startswith("codesign"))
        if not won[-1]:
            rep.notes.append(f"{cell[0]} across, {cell[1]} thread(s), {cell[2]}: {best['library']} is the fastest "
                             f"({1e3 * best['forward_s']:.1f} ms against codesign's "
                             f"{1e3 * min(r['forward_s'] for r in here if r['library'].startswith('codesign')):.1f}).")
    rep.notes.insert(1, f"codesign is the fastest in {sum(won)} of {len(cells)} cells.")
    table = []
    for r in rows:
        base = next(b for b in rows if b["samples"] == r["samples"] and b["threads"] == r["threads"]
                    and b["dtype"] == r["dtype"] and b["codesign_forward_backward_s"] is not None)
        fb = base["codesign_forward_backward_s"]
        chain = base.get("codesign_chain_s")
        grad = (f"codesign f+b {1e3 * fb:.1f} ms" + (f"; chain {1e3 * chain:.0f} ms" if chain else "") if r is base else
                f"{11 * r['forward_s'] / fb:.1f}x codesign f+b" if not r["library"].startswith("codesign") else "-")
        table.append([r["samples"], r["threads"], r["dtype"], r["library"], 1e3 * r["forward_s"],
                      r["forward_s"] / base["forward_s"], r["lsr_sampled"], r["max_rel_psf_diff"], grad])
    rep.tables.append(markdown_table(
        ["samples across", "threads", "dtype", "library", "forward ms", "time / codesign", "LSR (sampled)",
         "PSF agreement", "gradient: 11 forwards / codesign f+b"], table,
        {"forward ms": ".1f", "time / codesign": ".2f", "LSR (sampled)": ".6g", "PSF agreement": ".1e"}))
    return rep


def run(scale: str, out: Path) -> Report:
    data = measure(scale)
    write_json(out / "peers.json", data)
    return report(data)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "worker":
        worker(sys.argv[2:])
    else:
        from benchmarks.__main__ import standalone

        standalone(run)
