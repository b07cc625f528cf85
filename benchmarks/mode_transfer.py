"""Operator modes switched through the API over the real Modbus server: what each switch does to the box.

``python -m hvac_mpc.benchmarks.mode_transfer`` runs the daemon (MPC configured, its fallback the
thesis baseline) against the simulated plant behind :class:`hvac_mpc.daemon.modbus_sim.PlantModbusServer`
and switches MPC -> PID -> manual -> MPC with ``PUT /mode``. The reference is held across each
switch and changed between them by ``PUT /reference``, the last time while the box is in manual,
so the MPC switched in at the end faces a reference several degrees from the box. In manual the
operator starves the flow (blower at its minimum, outlets closed) and asks for the heater: the
daemon must refuse it (409) and log the refusal. Per switch it reports the largest actuator step
over the transfer window as a share of its rate limit, the largest change of the supply
temperature over the 10 s after the switch, and how far the box was from the reference at the
switch (docs/real-box.md, operator modes).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import tempfile
from pathlib import Path
from typing import Any

from hvac_mpc.contract import INPUTS
from hvac_mpc.daemon.config import SafetyConfig, config_from_mapping
from hvac_mpc.daemon.ctl import request
from hvac_mpc.daemon.loop import Daemon
from hvac_mpc.daemon.server import token_path

from .ports import free_port


#: Daemon time (s) of each switch and the mode it asks for.
SWITCHES = {200.0: "auto-pid", 400.0: "manual", 600.0: "auto-mpc"}
#: Reference changes between the switches (the last one while the operator holds the box in manual).
REFERENCES = {100.0: {"supply_temp_c": 17.0, "volume_flow_m3s": 0.035},
              280.0: {"supply_temp_c": 21.0, "volume_flow_m3s": 0.025},
              520.0: {"supply_temp_c": 16.0, "volume_flow_m3s": 0.032}}
#: Manual mode: (time s, actuators the operator sets). The flow starved, the heater asked for (refused),
#: then the operator's own open-loop setting: more blower, valve a mostly closed.
HEATER_REQUEST_S = 450.0
MANUAL = {420.0: {"blower_power_w": 30.0, "valve_m_pct": 0.0, "valve_f_pct": 0.0, "valve_w_pct": 0.0,
                  "heater_cmd_w": 0.0},
          HEATER_REQUEST_S: {"heater_cmd_w": 200.0},
          460.0: {"blower_power_w": 220.0, "valve_a_pct": 20.0, "valve_m_pct": 100.0, "valve_f_pct": 100.0,
                  "valve_w_pct": 100.0}}
TICKS = 880
#: Wall-time deadline of a controller step (s): generous, so a loaded machine does not swap in the fallback.
DEADLINE_S = 5.0
WINDOW_S = 10.0  # the supply temperature is checked over this long after a switch


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def run(workdir: str | Path, ramp: bool = True, seed: int = 5, safety: dict | None = None) -> dict[str, Any]:
    """Run the switches; returns the per-switch figures, the answers, the violations and the log path
    (the fault campaign checks every logged sample of it for safety, ``daemon_campaign.check_log``).

    ``ramp=False`` runs the same with the reference ramp off (``safety.transfer_ramp_* = 0``);
    ``safety`` overrides other ``[safety]`` keys; ``seed`` is the plant's noise seed."""
    from hvac_mpc.daemon.modbus_sim import PlantModbusServer
    from hvac_mpc.models.plant import SimulatedPlant

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    log = workdir / f"mode_transfer{'' if ramp else '_no_ramp'}.csv"
    for p in (log, log.with_suffix(".token")):
        p.unlink(missing_ok=True)
    port = free_port()  # for the Modbus server
    # heartbeat timeout: a load-tolerant 30 s of wall time (the plant runs in lockstep with the daemon)
    server = PlantModbusServer(SimulatedPlant(seed=seed), port=port, heartbeat_timeout_s=30.0).start()
    safety = {"reconnect_initial_s": 2.0, "reconnect_max_s": 8.0, **(safety or {})}
    if not ramp:
        safety.update({"transfer_ramp_c_per_s": 0.0, "transfer_ramp_m3s_per_s": 0.0})
    cfg = config_from_mapping({
        "loop": {"speedup": "max", "max_ticks": TICKS, "deadline_s": DEADLINE_S},
        "log": {"path": str(log), "fsync": False}, "api": {"port": 0},
        "controller": {"name": "mpc", "fallback": ["baseline"]}, "safety": safety,
        "reference": {"supply_temp_c": 20.0, "volume_flow_m3s": 0.03},
        "backend": {"kind": "modbus", "modbus": {"port": port, "timeout_s": 0.5}}})
    samples: list[dict] = []
    answers: dict[Any, tuple[int, Any]] = {}

    def hook(d: Daemon, sample: dict) -> None:
        samples.append({k: sample.get(k) for k in ("time_s", "controller", "supply_temp_c", "volume_flow_m3s",
                                                   "ref_supply_temp_c", "ref_volume_flow_m3s",
                                                   "working_reference", *INPUTS)})
        t = sample["time_s"]
        token = token_path(d.cfg).read_text().strip()

        def put(path: str, body: dict) -> tuple[int, Any]:
            return request(f"http://127.0.0.1:{d.api.port}", "PUT", path, json.dumps(body).encode(),
                           {"Content-Type": "application/json", "Authorization": f"Bearer {token}"}, 30.0)

        if t in SWITCHES:
            answers[t] = put("/mode", {"mode": SWITCHES[t]})
        if t in REFERENCES:
            answers[f"reference {t:.0f}"] = put("/reference", REFERENCES[t])
        if t in MANUAL:
            answers[f"manual {t:.0f}"] = put("/manual", MANUAL[t])

    records = _Records()
    logger = logging.getLogger("hvac_mpc.daemon")
    logger.addHandler(records)
    level = logger.level
    logger.setLevel(logging.INFO)
    try:
        daemon = Daemon(cfg, tick_hook=hook)
        code = daemon.run()
    finally:
        logger.removeHandler(records)
        logger.setLevel(level)
        server.stop()
    result = evaluate(samples, answers, cfg.safety)
    result.update({"exit_code": code, "log": str(log), "ramp": ramp, "seed": seed, "rows": len(samples),
                   "safety": cfg.safety,
                   "deadline_misses": daemon.counters["deadline_misses"],
                   "mode_history": [h["to"] for h in daemon.status()["mode_history"]],
                   "manual_refused": daemon.counters["manual_refused"],
                   "refusal_logged": [m for m in records.messages if "refused" in m and "heater" in m]})
    if code != 0:
        result["violations"].append(f"exit code {code}")
    if result["mode_history"] != list(SWITCHES.values()):
        result["violations"].append(f"mode history {result['mode_history']}")
    if result["manual_refused"] != 1 or not result["refusal_logged"]:
        result["violations"].append(f"heater refusal counted {result['manual_refused']} times, "
                                    f"logged {result['refusal_logged']}")
    return result


def switch_figures(by_t: dict[float, dict], ts: float, limits: dict[str, float], transfer_s: float,
                   dt_s: float = 1.0) -> dict[str, Any]:
    """One switch (requested at sample ``ts``, in force from the next): the reading and reference at
    it, the largest step of each actuator over the transfer window against its limit per sample,
    the largest change of the supply temperature over :data:`WINDOW_S`, and whether the logged
    reference stayed the same from 5 s before to :data:`WINDOW_S` after."""
    row = by_t[ts]
    window = [by_t[ts + k * dt_s] for k in range(0, int(transfer_s / dt_s) + 1)]
    steps = {n: max(abs(b[n] - a[n]) for a, b in zip(window, window[1:])) for n in INPUTS}
    ratio = {n: steps[n] / limits[n] for n in INPUTS}
    worst = max(ratio, key=ratio.get)
    t0 = row["supply_temp_c"]
    after = range(1, int(WINDOW_S / dt_s) + 1)
    held = {by_t[ts + k * dt_s]["ref_supply_temp_c"] for k in range(-5, after.stop)}
    return {"time_s": ts, "supply_temp_c": t0, "ref_supply_temp_c": row["ref_supply_temp_c"],
            "gap_c": t0 - row["ref_supply_temp_c"],
            "max_dT_10s_c": max(abs(by_t[ts + k * dt_s]["supply_temp_c"] - t0) for k in after),
            "max_step_over_limit": ratio[worst], "worst_actuator": worst, "steps": steps,
            "reference_held": len(held) == 1}


def evaluate(samples: list[dict], answers: dict, safety: SafetyConfig, dt_s: float = 1.0) -> dict[str, Any]:
    """Every switch's figures (:func:`switch_figures`), the heater refusal, how close the MPC is to its
    reference at the end, and the violations of the issue's check."""
    by_t = {s["time_s"]: s for s in samples}
    limits = {n: {"blower_power_w": safety.rate_blower_w_per_s, "heater_cmd_w": safety.rate_heater_w_per_s}.get(
        n, safety.rate_valve_pct_per_s) * dt_s for n in INPUTS}
    switches, violations = [], []
    previous = "auto-mpc"
    for ts, mode in SWITCHES.items():
        s = {"from": previous, "to": mode, "answer": answers.get(ts, (0, None))[0],
             **switch_figures(by_t, ts, limits, safety.transfer_s, dt_s)}
        switches.append(s)
        previous = mode
        if s["answer"] != 200:
            violations.append(f"switch to {mode} at {ts:.0f} s answered {answers.get(ts)}")
        if not s["reference_held"]:
            violations.append(f"reference not held across the switch at {ts:.0f} s")
        if s["max_step_over_limit"] > 1.0 + 1e-9:
            w = s["worst_actuator"]
            violations.append(f"{w} stepped {s['steps'][w]:.2f} after the switch to {mode} "
                              f"(limit {limits[w]:.1f} per sample)")
        if s["max_dT_10s_c"] > 0.5:
            violations.append(f"supply temperature moved {s['max_dT_10s_c']:.2f} C within {WINDOW_S:.0f} s of "
                              f"the switch to {mode}")
    refs = [s["ref_supply_temp_c"] for s in switches]
    if len(set(refs)) != len(refs):
        violations.append(f"reference not changed between the switches: {refs}")
    refused = answers.get(f"manual {HEATER_REQUEST_S:.0f}", (0, None))
    heater_after = [by_t[HEATER_REQUEST_S + k]["heater_cmd_w"] for k in range(1, 11)]
    if refused[0] != 409 or "heater refused" not in str(refused[1]) or any(h > 0 for h in heater_after):
        violations.append(f"heater at starved flow: answer {refused}, heater after it {max(heater_after)} W")
    last = samples[0]["time_s"] + (TICKS - 1) * dt_s  # the last controlled sample (then the shutdown)
    tail = [s for s in samples if last - 40.0 <= s["time_s"] <= last and s["controller"] == "mpc"]
    settled = max((abs(s["supply_temp_c"] - s["ref_supply_temp_c"]) for s in tail), default=math.inf)
    return {"switches": switches, "answers": {str(k): v for k, v in answers.items()}, "violations": violations,
            "refused_flow_m3s": by_t[HEATER_REQUEST_S]["volume_flow_m3s"], "refusal_answer": refused,
            "settled_error_c": settled,
            "ramp_s": sum(1 for s in samples if s["time_s"] > max(SWITCHES) and s["working_reference"])}


def format_result(r: dict[str, Any]) -> str:
    lines = [f"mode switches over Modbus (reference ramp {'on' if r['ramp'] else 'off'}): "
             f"{len(r['violations'])} violations"]
    for s in r["switches"]:
        lines.append(f"  {s['time_s']:.0f} s {s['from']} -> {s['to']}: answer {s['answer']}, box "
                     f"{s['supply_temp_c']:.2f} C, reference {s['ref_supply_temp_c']:.1f} C (gap {s['gap_c']:+.2f} C), "
                     f"max |dT| over {WINDOW_S:.0f} s {s['max_dT_10s_c']:.2f} C, largest actuator step "
                     f"{s['max_step_over_limit']:.2f} of its limit ({s['worst_actuator']})")
    lines.append(f"  heater at {r['refused_flow_m3s']:.4f} m3/s: {r['refusal_answer'][0]} "
                 f"({len(r['refusal_logged'])} log message); reference ramp after the last switch "
                 f"{r['ramp_s']} s; MPC within {r['settled_error_c']:.2f} C of its reference at the end")
    lines += [f"  VIOLATION {v}" for v in r["violations"]]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", default=None, help="folder of the log (default: a temporary one)")
    parser.add_argument("--no-ramp", action="store_true", help="the reference ramp off (the reference at once)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        r = run(args.workdir or tmp, ramp=not args.no_ramp)
    print(format_result(r))
    return 0 if not r["violations"] else 1


if __name__ == "__main__":
    sys.exit(main())
