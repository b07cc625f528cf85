"""What a sweep runs: the validated sweep spec and its expansion into single runs (docs/sweep.md).

A :class:`SweepSpec` (TOML or JSON file, or CLI options) names the axes: scenarios, noise seeds,
plants, inlet temperatures, controllers, MPC weights and horizons, model files. ``grid`` crosses
them all; ``lhs`` draws ``samples`` points with a Latin hypercube (``scipy.stats.qmc``), discrete
axes by index and continuous ranges (inlet temperature, weights, log-uniform) by value. Every point
is run with every controller, so each MPC run has a baseline run that differs only in the
controller. A :class:`RunSpec` holds every input of one run; its ``run_id`` is a hash of them, so
a resumed sweep recognises finished runs and any result row replays exactly.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import tomllib
from dataclasses import fields
from pathlib import Path
from typing import Literal

from pydantic import (BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator,
                      model_validator)

from hvac_mpc.mismatch import VARIANTS
from hvac_mpc.mpc.ocp import OcpSpec, Weights
from hvac_mpc.validation import describe_error

from . import scenarios as scenario_defs

#: Plants of the project's own simulator: nominal parameters, or the bench's seeded parameter
#: perturbation (``benchmarks/perturbation.py``) drawn from the run's seed.
SIMULATED_PLANTS = ("simulated", "simulated_perturbed")
#: Every plant name a sweep accepts: the two above and the independent simulator's variants.
PLANTS = SIMULATED_PLANTS + tuple(VARIANTS)
CONTROLLERS = ("mpc", "baseline")
WEIGHT_NAMES = tuple(f.name for f in fields(Weights))


class InvalidSweep(ValueError):
    """A sweep spec or a run spec that does not validate (the message names the field)."""


def file_hash(path: str | Path) -> str:
    """SHA-256 of a file's bytes (hex), recorded with each run that uses the file."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


class RunSpec(BaseModel):
    """Every input of one closed-loop run; equal inputs give equal ``run_id`` and equal figures.

    ``length``: the scenario as defined ("full") or its short version ("quick", ``Scenario.quick``);
    ``max_duration_s`` then cuts it further. ``inlet_temp_c`` replaces the scenario's inlet air
    temperature (None keeps it). ``weights`` (``Weights`` fields) and ``stage_durations_s`` (the
    horizon, ``OcpSpec``) change the MPC only; a baseline run carries neither.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    scenario: str
    length: Literal["full", "quick"] = "quick"
    max_duration_s: float | None = Field(None, ge=10.0, le=100_000.0)
    seed: int = Field(0, ge=0, le=2**32 - 1)
    plant: str = "simulated"
    inlet_temp_c: float | None = Field(None, ge=-30.0, le=50.0)
    controller: Literal["mpc", "baseline"] = "mpc"
    weights: dict[str, float] = Field(default_factory=dict)
    stage_durations_s: tuple[float, ...] | None = None
    model_file: str | None = None
    model_hash: str | None = None

    @field_validator("scenario")
    @classmethod
    def _scenario(cls, v: str) -> str:
        known = scenario_defs.all_scenarios()
        if v not in known:
            raise ValueError(f"unknown scenario {v!r}; allowed: {', '.join(known)}")
        return v

    @field_validator("plant")
    @classmethod
    def _plant(cls, v: str) -> str:
        if v not in PLANTS:
            raise ValueError(f"unknown plant {v!r}; allowed: {', '.join(PLANTS)}")
        return v

    @field_validator("weights")
    @classmethod
    def _weights(cls, v: dict[str, float]) -> dict[str, float]:
        _check_weights(v)
        return dict(sorted(v.items()))

    @field_validator("stage_durations_s")
    @classmethod
    def _stages(cls, v):
        if v is not None:
            _check_stages(v)
        return v

    @model_validator(mode="after")
    def _baseline_plain(self) -> "RunSpec":
        if self.controller == "baseline" and (self.weights or self.stage_durations_s is not None):
            raise ValueError("weights and stage_durations_s apply to the MPC only; a baseline run carries neither")
        if (self.model_file is None) != (self.model_hash is None):
            raise ValueError("model_file and model_hash go together (the hash of the file the run used)")
        return self

    def inputs(self) -> dict:
        """The inputs as plain JSON-able values (what the run id hashes)."""
        return self.model_dump(mode="json")

    @property
    def run_id(self) -> str:
        """16 hex digits of the SHA-256 of the canonical JSON of the inputs."""
        text = json.dumps(self.inputs(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def pair_key(self) -> str:
        """Everything but the controller and its settings: an MPC run and its baseline run share it."""
        d = self.inputs()
        for k in ("controller", "weights", "stage_durations_s"):
            d.pop(k)
        return json.dumps(d, sort_keys=True, separators=(",", ":"))


def _check_weights(v: dict[str, float]) -> None:
    unknown = [k for k in v if k not in WEIGHT_NAMES]
    if unknown:
        raise ValueError(f"unknown weight(s) {unknown}; allowed: {', '.join(WEIGHT_NAMES)}")
    try:
        Weights(**v).validate("weights")
    except ValueError as exc:
        raise ValueError(str(exc)) from None


def _check_stages(v) -> None:
    try:
        OcpSpec(stage_durations_s=tuple(v)).validate(1.0, "stage_durations_s")
    except ValueError as exc:
        raise ValueError(str(exc)) from None


class SweepSpec(BaseModel):
    """The axes of a sweep (all lists are crossed in ``grid`` mode; see the module docstring).

    ``inlet_temps_c``/``weights`` are the grid values; ``inlet_temp_range_c``/``weight_ranges``
    are the ``lhs`` ranges (weights log-uniform), used instead of the lists when given.
    ``horizons``: stage-duration lists (s, ``OcpSpec.stage_durations_s``), null for the default.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    sampling: Literal["grid", "lhs"] = "grid"
    samples: int = Field(0, ge=0, le=1_000_000)
    sample_seed: int = Field(0, ge=0, le=2**32 - 1)
    scenarios: list[str] = Field(default_factory=lambda: list(scenario_defs.all_scenarios()), min_length=1)
    length: Literal["full", "quick"] = "quick"
    max_duration_s: float | None = Field(None, ge=10.0, le=100_000.0)
    seeds: list[int] = Field(default_factory=lambda: [0], min_length=1)
    plants: list[str] = Field(default_factory=lambda: ["simulated"], min_length=1)
    controllers: list[Literal["mpc", "baseline"]] = Field(default_factory=lambda: list(CONTROLLERS), min_length=1)
    inlet_temps_c: list[float | None] = Field(default_factory=lambda: [None], min_length=1)
    inlet_temp_range_c: tuple[float, float] | None = None
    weights: list[dict[str, float]] = Field(default_factory=lambda: [{}], min_length=1)
    weight_ranges: dict[str, tuple[float, float]] = Field(default_factory=dict)
    horizons: list[list[float] | None] = Field(default_factory=lambda: [None], min_length=1)
    model_files: list[str | None] = Field(default_factory=lambda: [None], min_length=1)

    @field_validator("scenarios", "plants")
    @classmethod
    def _names(cls, v: list[str], info: ValidationInfo) -> list[str]:
        check = RunSpec._scenario if info.field_name == "scenarios" else RunSpec._plant
        for name in v:
            check(name)
        return list(dict.fromkeys(v))

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, v: list[int]) -> list[int]:
        bad = [s for s in v if not 0 <= s <= 2**32 - 1]
        if bad:
            raise ValueError(f"seeds must be integers in [0, 4294967295], got {bad}")
        return list(dict.fromkeys(v))

    @field_validator("inlet_temps_c")
    @classmethod
    def _inlets(cls, v):
        bad = [t for t in v if t is not None and not (math.isfinite(t) and -30.0 <= t <= 50.0)]
        if bad:
            raise ValueError(f"inlet temperatures must lie in [-30, 50] degC, got {bad}")
        return v

    @field_validator("inlet_temp_range_c")
    @classmethod
    def _inlet_range(cls, v):
        if v is not None and not (-30.0 <= v[0] <= v[1] <= 50.0):
            raise ValueError(f"expected [low, high] with -30 <= low <= high <= 50 degC, got {list(v)}")
        return v

    @field_validator("weights", "horizons")
    @classmethod
    def _each(cls, v, info: ValidationInfo):
        check = _check_weights if info.field_name == "weights" else _check_stages
        for item in v:
            if item is not None:
                check(item)
        return v

    @field_validator("weight_ranges")
    @classmethod
    def _weight_ranges(cls, v):
        for k, (lo, hi) in v.items():
            if k not in WEIGHT_NAMES:
                raise ValueError(f"unknown weight {k!r}; allowed: {', '.join(WEIGHT_NAMES)}")
            if not (0.0 < lo <= hi <= 1e6):
                raise ValueError(f"{k}: expected [low, high] with 0 < low <= high <= 1e6 (log-uniform), got {[lo, hi]}")
        return v

    @field_validator("model_files")
    @classmethod
    def _model_files(cls, v):
        missing = [f for f in v if f is not None and not Path(f).is_file()]
        if missing:
            raise ValueError(f"model file(s) not found: {missing}")
        return v

    @model_validator(mode="after")
    def _mode(self) -> "SweepSpec":
        if self.sampling == "lhs" and self.samples < 1:
            raise ValueError("samples: lhs sampling needs samples >= 1 (range [1, 1000000])")
        if self.sampling == "grid" and (self.inlet_temp_range_c is not None or self.weight_ranges):
            raise ValueError("inlet_temp_range_c and weight_ranges are lhs ranges; a grid takes inlet_temps_c "
                             "and weights lists")
        return self


def load_spec(path: str | Path) -> SweepSpec:
    """A :class:`SweepSpec` from a TOML or JSON file; :class:`InvalidSweep` names the bad field."""
    path = Path(path)
    if not path.is_file():
        raise InvalidSweep(f"sweep spec {path} does not exist")
    text = path.read_text()
    try:
        data = json.loads(text) if path.suffix.lower() == ".json" else tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise InvalidSweep(f"sweep spec {path}: not valid {path.suffix.lstrip('.').upper() or 'TOML'} ({exc})") from None
    return make_spec(data, f"{path}: ")


def make_spec(data: dict, prefix: str = "") -> SweepSpec:
    """A validated :class:`SweepSpec` from plain data; :class:`InvalidSweep` names the bad field."""
    try:
        return SweepSpec.model_validate(_nulls(data))
    except ValidationError as exc:
        raise InvalidSweep(describe_error(exc, prefix)) from None


def _nulls(data: dict) -> dict:
    """TOML has no null: the string "default" (or "none") stands for it in the list axes."""
    out = dict(data)
    for key in ("inlet_temps_c", "horizons", "model_files"):
        if isinstance(out.get(key), list):
            out[key] = [None if isinstance(x, str) and x.lower() in ("default", "none") else x for x in out[key]]
    return out


# ---------------------------------------------------------------------------- expansion
def _run(spec: SweepSpec, controller: str, scenario: str, seed: int, plant: str, inlet, weights: dict,
         horizon, model_file, hashes: dict) -> RunSpec:
    mpc = controller == "mpc"
    return RunSpec(scenario=scenario, length=spec.length, max_duration_s=spec.max_duration_s, seed=seed, plant=plant,
                   inlet_temp_c=inlet, controller=controller, weights=weights if mpc else {},
                   stage_durations_s=tuple(horizon) if (mpc and horizon is not None) else None,
                   model_file=model_file, model_hash=hashes.get(model_file))


def expand(spec: SweepSpec) -> list[RunSpec]:
    """All runs of a sweep, without repeats (baseline runs do not multiply with MPC settings)."""
    hashes = {f: file_hash(f) for f in spec.model_files if f is not None}
    points = _grid_points(spec) if spec.sampling == "grid" else _lhs_points(spec)
    runs: dict[str, RunSpec] = {}
    for p in points:
        for c in spec.controllers:
            r = _run(spec, c, *p, hashes=hashes)
            runs.setdefault(r.run_id, r)
    return list(runs.values())


def _grid_points(spec: SweepSpec):
    return itertools.product(spec.scenarios, spec.seeds, spec.plants, spec.inlet_temps_c, spec.weights,
                             spec.horizons, spec.model_files)


def _pick(options: list, u: float):
    return options[min(int(u * len(options)), len(options) - 1)]


def _lhs_points(spec: SweepSpec) -> list[tuple]:
    """``samples`` Latin-hypercube points: one column per axis (discrete by index, ranges by value)."""
    from scipy.stats import qmc

    wnames = sorted(spec.weight_ranges)
    d = 7 + len(wnames)
    u = qmc.LatinHypercube(d=d, seed=spec.sample_seed).random(spec.samples)
    out = []
    for row in u:
        if spec.inlet_temp_range_c is not None:
            lo, hi = spec.inlet_temp_range_c
            inlet = float(round(lo + row[3] * (hi - lo), 6))
        else:
            inlet = _pick(spec.inlet_temps_c, row[3])
        if wnames:
            weights = {n: round(float(math.exp(math.log(spec.weight_ranges[n][0]) + row[7 + i] * math.log(
                spec.weight_ranges[n][1] / spec.weight_ranges[n][0]))), 9) for i, n in enumerate(wnames)}
        else:
            weights = _pick(spec.weights, row[4])
        out.append((_pick(spec.scenarios, row[0]), _pick(spec.seeds, row[1]), _pick(spec.plants, row[2]), inlet,
                    weights, _pick(spec.horizons, row[5]), _pick(spec.model_files, row[6])))
    return out


def shorten(scenario: scenario_defs.Scenario, max_duration_s: float | None) -> scenario_defs.Scenario:
    """The scenario cut to at most ``max_duration_s`` (warm-up kept whole if it fits, then segments)."""
    from dataclasses import replace

    if max_duration_s is None or scenario.duration_s <= max_duration_s:
        return scenario
    warm = scenario.warmup
    if warm.duration_s >= max_duration_s - 1.0:
        warm = replace(warm, duration_s=max(1.0, max_duration_s / 2.0))
    left = max_duration_s - warm.duration_s
    segs = []
    for s in scenario.segments:
        if left < 1.0:
            break
        segs.append(replace(s, duration_s=min(s.duration_s, left)))
        left -= segs[-1].duration_s
    return replace(scenario, warmup=warm, segments=tuple(segs))


def scenario_of(run: RunSpec) -> scenario_defs.Scenario:
    """The scenario a run plays: chosen length, cut, inlet temperature replaced if asked."""
    from dataclasses import replace

    sc = scenario_defs.all_scenarios()[run.scenario]
    if run.length == "quick":
        sc = sc.quick()
    sc = shorten(sc, run.max_duration_s)
    if run.inlet_temp_c is not None:
        sc = replace(sc, inlet_temp_c=float(run.inlet_temp_c))
    return sc

