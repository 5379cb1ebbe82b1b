"""Named, versioned scenario suites, committed as data (the JSON files beside this module).

| suite   | kind    | what                                                                    |
|---------|---------|-------------------------------------------------------------------------|
| nominal | list    | the paper's cycle, per braking alternative                              |
| train   | sampler | uniform over the scenario ranges, seeded (seed stream ``TRAIN_STREAM``) |
| test    | list    | 50 draws per braking alternative, from the same ranges (``TEST_STREAM``) |
| corners | list    | each field at each end of its range, the others nominal                 |

The ``test`` list was drawn once by :func:`draw` with its own seed stream (``scripts/make_suites.py``
writes the files); a test checks the file against a fresh draw and against ``train``'s stream.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from wl_env.cycle import BRAKING_MODES, check_braking
from wl_env.params import LoaderParams, plain, shown
from wl_env.scenario import FIELDS, Scenario

FOLDER = Path(__file__).resolve().parent
SUITES = ("nominal", "train", "test", "corners")
TRAIN_STREAM, TEST_STREAM = 0, 1  # SeedSequence spawn keys: the two streams never share a draw
ROOT_ENTROPY = 20261201  # the suites' root seed
MAX_SAMPLE = 100_000  # scenarios a spread() gives at most: agents.evaluate.MAX_EPISODES, the episodes of one evaluation
# Drawn values are rounded to these decimals (readable files; far finer than any effect).
ROUNDING = {"payload": -1, "reverse_distance": 2, "forward_distance": 2, "rolling_resistance": 4,
            "dump_height": 2, "start_engine_speed": 0, "start_bucket_height": 2}


def corner_scenarios(braking: str) -> list[Scenario]:
    """The 2^7 = 128 corners of the scenario ranges, in binary order of (payload, reverse, forward, c_r, dump
    height, start speed, start height), low = 0."""
    return [Scenario(**{n: (f.lo, f.hi)[b] for (n, f), b in zip(FIELDS.items(), bits, strict=True)},
                     braking=check_braking(braking))
            for bits in itertools.product((0, 1), repeat=len(FIELDS))]


def draw(rng: np.random.Generator, braking: str) -> Scenario:
    """One scenario, uniform over the ranges (rounded, :data:`ROUNDING`)."""
    values = {}
    for name, spec in FIELDS.items():
        values[name] = float(np.clip(round(float(rng.uniform(spec.lo, spec.hi)), ROUNDING[name]), spec.lo, spec.hi))
    return Scenario(braking=check_braking(braking), **values)


def stream(which: int, seed: int = 0) -> np.random.Generator:
    """The generator of a suite's seed stream (TRAIN_STREAM or TEST_STREAM) for a seed."""
    return np.random.default_rng(np.random.SeedSequence(ROOT_ENTROPY, spawn_key=(which, seed)))


@dataclass(frozen=True)
class Suite:
    """A named, versioned set of scenarios: a fixed list, or (``train``) a seeded sampler."""

    name: str
    version: int
    description: str
    scenarios: tuple[Scenario, ...] = ()  # empty for a sampler
    sampler: bool = False

    def of(self, braking: str) -> tuple[Scenario, ...]:
        """The list's scenarios of one braking alternative."""
        check_braking(braking)
        if self.sampler:
            raise ValueError(f"suite {self.name!r} is a sampler, not a list: use sample()")
        return tuple(s for s in self.scenarios if s.braking == braking)

    def spread(self, braking: str, n: int | None = None) -> tuple[Scenario, ...]:
        """``n`` of the list's scenarios of one braking alternative, evenly spread over it (all if n is None
        or larger): a fixed sample, the same every run. A sampler suite gives its first n draws of seed 0."""
        n = plain(n)  # (a numpy integer as the int it holds, as MPCConfig and Scenario take it)
        if n is not None and (isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_SAMPLE):
            # (a sampler drew 10**11 scenarios, minutes and gigabytes before any check)
            raise ValueError(f"the sample size (--sample) must be an integer in [1, {MAX_SAMPLE}] or None, got {shown(n)}")
        if self.sampler:
            if not n:
                raise ValueError(f"suite {self.name!r} is a sampler: say how many scenarios to draw")
            rng = stream(TRAIN_STREAM)
            return tuple(draw(rng, braking) for _ in range(n))
        options = self.of(braking)
        if n is None or n >= len(options):
            return options
        return tuple(options[round(i * (len(options) - 1) / max(n - 1, 1))] for i in range(n))

    def check_machine(self, machine: LoaderParams, braking: str) -> None:
        """ValueError naming the suite, the scenario and its field if ``machine`` cannot drive one of the suite's
        cycles: every scenario of the list, or every corner of the ranges a sampler draws from (each field's
        range maps onto one machine parameter independently, so the corners bound them all). Checked when an
        env takes the suite, not at the draw that fails mid-training."""
        for sc in corner_scenarios(braking) if self.sampler else self.of(braking):
            try:
                sc.params(machine)
            except ValueError as exc:
                raise ValueError(f"suite {self.name!r} holds a cycle this machine cannot drive ({sc.label()}): "
                                 f"{exc}") from None

    def sample(self, rng: np.random.Generator, braking: str) -> Scenario:
        """One scenario of the braking alternative: a fresh draw (sampler) or one of the list, uniformly."""
        if not isinstance(rng, np.random.Generator):  # (a seed was an AttributeError; a RandomState drew from a sampler)
            raise ValueError(f"rng must be a numpy Generator (np.random.default_rng(seed)), got {shown(rng)} "
                             f"({type(rng).__name__})")
        if self.sampler:
            return draw(rng, braking)
        options = self.of(braking)
        return options[int(rng.integers(len(options)))]


def load_suite(name: str) -> Suite:
    """The suite ``name`` (one of :data:`SUITES`), read from its file and validated (once per process)."""
    if not isinstance(name, str) or name not in SUITES:  # (a list was the cache's "unhashable type")
        raise ValueError(f"unknown suite {shown(name)}; suites: {SUITES}")
    return _load_suite(name)


@cache
def _load_suite(name: str) -> Suite:
    path = FOLDER / f"{name}.json"
    try:  # (every problem names the file: a bare JSONDecodeError, OverflowError or RecursionError did not)
        data = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(data, dict):
            raise ValueError(f"a JSON {type(data).__name__}, not an object")
        kind, version, listed = data.get("kind"), data.get("version"), data.get("scenarios")
        if kind not in ("list", "sampler"):
            raise ValueError(f"kind must be 'list' or 'sampler', got {shown(kind)}")
        if isinstance(version, bool) or not (isinstance(version, int) and 1 <= version <= 10**6):
            raise ValueError(f"version must be an integer in [1, 1000000], got {shown(version)}")
        if not isinstance(data.get("description"), str):
            raise ValueError(f"description must be a string, got {shown(data.get('description'))}")
        if kind == "sampler" and listed is not None:
            raise ValueError("a sampler suite draws its scenarios: it lists none")
        if kind == "list" and not (isinstance(listed, list) and listed):
            raise ValueError(f"a list suite needs a non-empty list of scenarios, got {shown(listed)}")
        scenarios = tuple(Scenario.from_dict(d) for d in listed or ())
        suite = Suite(name=data.get("name"), version=version, description=data["description"],
                      scenarios=scenarios, sampler=kind == "sampler")
    except RecursionError:
        raise ValueError(f"suite file {path} is invalid: not valid JSON (nested too deeply)") from None
    except (KeyError, ValueError, TypeError, OverflowError) as exc:
        raise ValueError(f"suite file {path} is invalid: {exc}") from None
    if suite.name != name:
        raise ValueError(f"suite file {path} names itself {suite.name!r}")
    return suite


def suite_files() -> dict[str, dict[str, Any]]:
    """The suites' file contents as :func:`draw` and the corners define them (``scripts/make_suites.py``)."""
    nominal = [Scenario.nominal(b).to_dict() for b in BRAKING_MODES]
    corners = []
    for b in BRAKING_MODES:
        for name, spec in FIELDS.items():
            for end in (spec.lo, spec.hi):
                corners.append(Scenario(braking=b, **{name: end}).to_dict())
    test = []
    rng = stream(TEST_STREAM)
    draws = [draw(rng, "service") for _ in range(50)]
    for b in BRAKING_MODES:  # the same 50 cycles for both alternatives: their fronts compare per cycle
        test += [s.replace(braking=b).to_dict() for s in draws]
    return {
        "nominal": {"name": "nominal", "version": 1, "kind": "list",
                    "description": "the paper's cycle, per braking alternative", "scenarios": nominal},
        "train": {"name": "train", "version": 1, "kind": "sampler",
                  "description": "uniform over the scenario ranges, rounded (wl_env.suites.draw), seed stream "
                                 f"spawn_key=({TRAIN_STREAM}, seed) of SeedSequence({ROOT_ENTROPY})",
                  "ranges": {n: [s.lo, s.hi] for n, s in FIELDS.items()}},
        "test": {"name": "test", "version": 1, "kind": "list",
                 "description": f"50 cycles drawn once as train's, seed stream spawn_key=({TEST_STREAM}, 0) of "
                                f"SeedSequence({ROOT_ENTROPY}), each with both braking alternatives",
                 "scenarios": test},
        "corners": {"name": "corners", "version": 1, "kind": "list",
                    "description": "each field at each end of its range, the others nominal, per braking alternative",
                    "scenarios": corners},
    }
