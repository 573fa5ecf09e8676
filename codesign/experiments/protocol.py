"""The protocol of an experiment module, declared as one checked object: what ``+experiment=NAME`` reads, writes,
resumes and shrinks, so that the runner (codesign/experiments/__init__.py), the debug shrink and the tests derive
what they need from it instead of keeping their own lists.

An experiment is one module of this package with ``EXPERIMENT = Experiment(...)`` and ``run(cfg, run_dir,
device)``, plus its YAML in conf/experiment/ (the group overrides it composes with, e.g. a preset).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping

# Root keys every experiment has (conf/config.yaml and its groups).
COMMON_KEYS = ("task", "seed", "device", "threads", "deterministic", "optics", "material", "mask", "sensor", "model",
               "data", "trainer", "metrics", "logging", "evaluate", "debug")
# The common keys every experiment reads; the others only where ``reads`` names them (all of them when None).
ALWAYS_READ = ("task", "seed", "device", "threads", "deterministic", "logging", "debug")


@dataclass(frozen=True)
class Experiment:
    """What an experiment module declares.

    summary: one line for ``codesign --help``.
    root_keys: root keys it reads besides COMMON_KEYS (any other root key is refused, e.g. a typo added with +).
    reads: the common groups it reads besides ALWAYS_READ (None: all of COMMON_KEYS); debug=smoke shrinks only these.
    outputs: the fixed file names it writes in its run directory (each checked to be writable before any work).
    resumes: a killed run started again on its folder continues from its checkpoint (else such a folder is refused).
    distributed: it trains networks and runs data-parallel under torchrun.
    measured_psf: optics.psf_file replaces its computed PSF (codesign/optics/measured.py); refused otherwise.
    first_work: the module attribute where its real work starts: ``name``, ``Class.method``, or ``factory().method``
        (the method of the object the factory returns); every check must come before it (the input tests replace
        it with a sentinel and expect a configuration error first).
    smoke: debug=smoke's shrink of the keys this experiment alone has (dotted key -> value; the common shrink is
        conf/debug/smoke.yaml).
    """

    summary: str
    first_work: str
    root_keys: tuple[str, ...] = ()
    reads: tuple[str, ...] | None = None
    outputs: tuple[str, ...] = ("metrics.json",)
    resumes: bool = False
    distributed: bool = False
    measured_psf: bool = False
    smoke: Mapping[str, object] = field(default_factory=dict)

    def __post_init__(self) -> None:
        def strings(name: str, values) -> tuple[str, ...]:
            if isinstance(values, str) or not all(isinstance(v, str) and v for v in values):
                raise TypeError(f"Experiment.{name} must be a tuple of non-empty strings, got {values!r}")
            return tuple(values)

        if not (isinstance(self.summary, str) and self.summary and "\n" not in self.summary):
            raise TypeError(f"Experiment.summary must be one non-empty line, got {self.summary!r}")
        if not (isinstance(self.first_work, str) and self.first_work):
            raise TypeError("Experiment.first_work must name the module attribute where the real work starts")
        object.__setattr__(self, "root_keys", strings("root_keys", self.root_keys))
        common = sorted(set(self.root_keys) & set(COMMON_KEYS))
        if common:
            raise ValueError(f"Experiment.root_keys: {common} are common keys (COMMON_KEYS), not the experiment's own")
        if self.reads is not None:
            object.__setattr__(self, "reads", strings("reads", self.reads))
            other = sorted(set(self.reads) - set(COMMON_KEYS))
            if other:
                raise ValueError(f"Experiment.reads: {other} are not common keys; allowed: {', '.join(COMMON_KEYS)}")
        object.__setattr__(self, "outputs", strings("outputs", self.outputs))
        if any("/" in o for o in self.outputs) or "metrics.json" not in self.outputs:
            raise ValueError(f"Experiment.outputs: plain file names, metrics.json among them; got {self.outputs}")
        for flag in ("resumes", "distributed", "measured_psf"):
            if not isinstance(getattr(self, flag), bool):
                raise TypeError(f"Experiment.{flag} must be true or false")
        roots = sorted({k.split(".", 1)[0] for k in self.smoke} - set(self.root_keys))
        if roots:
            raise ValueError(f"Experiment.smoke shrinks keys under {roots}, which are not this experiment's own root "
                             f"keys {self.root_keys} (the common shrink is conf/debug/smoke.yaml)")
        object.__setattr__(self, "smoke", MappingProxyType(dict(self.smoke)))

    @property
    def all_root_keys(self) -> tuple[str, ...]:
        """Every root key it accepts: COMMON_KEYS + its own."""
        return COMMON_KEYS + self.root_keys

    @property
    def read_keys(self) -> tuple[str, ...]:
        """The root keys it actually reads: what debug=smoke shrinks and says it shrank."""
        if self.reads is None:
            return self.all_root_keys
        return ALWAYS_READ + self.reads + self.root_keys
