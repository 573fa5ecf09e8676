"""What a training records of its loss terms for the console, the checkpoint and metrics.json: the first logged
terms, the last ones, the lowest value of each reconstruction term, and from them whether the run diverged."""
from __future__ import annotations

import logging
import math

log = logging.getLogger("codesign.train")

# A reconstruction term ending this many times above its lowest logged value marks the run as diverged (a sound run
# ends within a few times its lowest; learning rates 5000x the default end 4.8e4x above it after 16 smoke steps).
DIVERGED_FACTOR = 100.0


def reconstruction_terms(terms: dict) -> list[str]:
    """The reconstruction loss terms (rec1, rec2, ...: every restorer's fit to the target) among logged ``terms``;
    the adversarial and total terms change sign and scale by design, so divergence is judged on these."""
    return [k for k in terms if k.startswith("rec")]


class LossRecord:
    """The logged loss terms of a run, kept across resumes (they travel in the checkpoint's ``record``)."""

    def __init__(self):
        self.first: dict = {}  # the terms of the run's first logged step
        self.last: dict = {}
        self.lowest: dict = {}  # the lowest logged value of each reconstruction term

    def add(self, values: dict, counted: bool = True) -> None:
        """A logging step's terms (global-batch means); ``counted``: they update the lowest values (the extra lines
        of a resume or a stop signal are not: a resumed run records the divergence figures of an uninterrupted
        one)."""
        self.first = self.first or values
        self.last = values
        for k in reconstruction_terms(values) if counted else ():
            if math.isfinite(values[k]):
                self.lowest[k] = min(self.lowest.get(k, math.inf), values[k])

    def divergence(self) -> dict:
        """``diverged`` (1 or 0): a reconstruction term ended non-finite or more than DIVERGED_FACTOR times above
        its lowest logged value; ``loss_growth``: the largest last / lowest ratio; ``loss_growth_term``."""
        growth, worst = 1.0, None
        for k in reconstruction_terms(self.last):
            last, low = self.last[k], self.lowest.get(k)
            ratio = math.inf if not math.isfinite(last) else last / low if low else 1.0
            if ratio > growth:
                growth, worst = ratio, k
        return {"diverged": int(growth > DIVERGED_FACTOR), "loss_growth": growth, "loss_growth_term": worst}

    def warn_if_diverged(self) -> None:
        """One console warning when the training diverged (``divergence``)."""
        d = self.divergence()
        if d["diverged"]:
            k = d["loss_growth_term"]
            log.warning("training DIVERGED: the reconstruction term %s ended at %.4g, %.3gx its lowest logged value "
                        "%.4g; the results are not a trained network's (lower trainer.lr_weights / "
                        "trainer.lr_biases; metrics.json: diverged = 1)", k, self.last[k], d["loss_growth"],
                        self.lowest.get(k, math.nan))

    def state_dict(self) -> dict:
        """The first and the lowest logged terms (what a resumed run's divergence check needs)."""
        return {"first_terms": self.first, "lowest_terms": self.lowest}

    def load_state_dict(self, record: dict) -> None:
        """Restore a ``state_dict`` (absent entries: empty)."""
        self.first = dict(record.get("first_terms", {}) or {})
        self.lowest = dict(record.get("lowest_terms", {}) or {})
