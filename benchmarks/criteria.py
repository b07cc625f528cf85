"""Issue 4's 'must show' criteria per scenario, judged from the figures, with the reason when not met.

For each scenario: the MPC beats the baseline on supply-temperature IAE and on outlet-flow RMS
error, without using more electric energy; the aims: temperature IAE at most 0.4 times the
baseline's, and on cooling scenarios every temperature step within +-0.5 C in under 20 s.
Every sentence is generated from the numbers of the same run.
"""

from __future__ import annotations

from typing import Mapping

from .metrics import STEADY_AFTER_S, TEMP_BAND_C

IAE_AIM_RATIO = 0.4
#: Flow-IAE ratio above which a met comparison carries a caveat on flow tracking.
FLOW_NOTE_RATIO = 1.2
COOLING_TIME_AIM_S = 20.0

M3H = 3600.0


def _fmt_ratio(r) -> str:
    return "n/a" if r is None else f"{r:.2f}"


def _why_temperature(mpc: Mapping, base: Mapping, md: Mapping, bd: Mapping) -> str:
    parts = []
    if md.get("steady_samples"):
        share = md["temp_iae_steady_cs"] / mpc["temp_iae_cs"] if mpc["temp_iae_cs"] > 0 else 0.0
        parts.append(f"{share:.0%} of the MPC's IAE accrues more than {STEADY_AFTER_S:.0f} s after a temperature "
                     "step or the start of scoring "
                     f"(mean |error| there {md['temp_mean_abs_steady_c']:.2f} C, baseline "
                     f"{bd['temp_mean_abs_steady_c']:.2f} C)")
    slower = [(m, b) for m, b in zip(md["temperature_steps"], bd["temperature_steps"])
              if (m["time_to_band_s"] is None and b["time_to_band_s"] is not None)
              or (None not in (m["time_to_band_s"], b["time_to_band_s"]) and m["time_to_band_s"] > b["time_to_band_s"])]
    if slower:
        desc = ", ".join(f"{m['from']:.1f}->{m['to']:.1f} C at {m['time_s']:.0f} s "
                         f"({_t(m['time_to_band_s'])} vs {_t(b['time_to_band_s'])})" for m, b in slower[:4])
        parts.append(f"slower to +-{TEMP_BAND_C} C on {len(slower)} of {len(md['temperature_steps'])} steps: {desc}")
    for m, b in zip(md["temperature_steps"], bd["temperature_steps"]):
        if m["time_to_band_s"] is None:
            parts.append(f"{m['from']:.1f}->{m['to']:.1f} C at {m['time_s']:.0f} s never settles within "
                         f"+-{TEMP_BAND_C} C: {_end(m)} at its end (baseline {_end(b)})")
    if mpc["temp_overshoot_max_c"] > base["temp_overshoot_max_c"] + 0.05:
        parts.append(f"overshoot up to {mpc['temp_overshoot_max_c']:.2f} C against {base['temp_overshoot_max_c']:.2f} C")
    parts.extend(_common(mpc, md))
    return "; ".join(parts) if parts else "no single cause stands out in the step figures"


def _end(step: Mapping) -> str:
    e = step.get("final_error")
    if e is None:
        return "n/a"
    return f"{abs(e):.2f} C {'above' if e > 0 else 'below'} the reference"


def _lag_floor(mpc: Mapping, base: Mapping) -> str:
    """The lag-only IAE against the baseline's: how low the ratio goes without overshooting the air."""
    ideal = mpc.get("ideal_temp_iae_cs")
    if not ideal or not base["temp_iae_cs"]:
        return ""
    r = ideal / base["temp_iae_cs"]
    text = (f"a response limited only by the thermocouple lag (air at the reference from the step on, no actuator "
            f"limit, no overshoot) scores {ideal:.1f} C s, {r:.2f} x the baseline's IAE")
    if r > IAE_AIM_RATIO:
        text += ", so the aim needs the air temperature to overshoot on purpose"
    return text


def _why_outlets(mpc: Mapping, base: Mapping, md: Mapping, bd: Mapping) -> str:
    parts = []
    worse = [(o, md["outlet_rms_m3s"][o], bd["outlet_rms_m3s"][o]) for o in md["outlet_rms_m3s"]
             if md["outlet_rms_m3s"][o] is not None and bd["outlet_rms_m3s"][o] is not None
             and md["outlet_rms_m3s"][o] > bd["outlet_rms_m3s"][o]]
    if worse:
        parts.append("larger RMS error at " + ", ".join(
            f"{o.split('_')[1]} ({m * M3H:.1f} vs {b * M3H:.1f} m3/h)" for o, m, b in worse))
    parts.append(f"total-flow IAE ratio {_fmt_ratio(_r(mpc['flow_iae_m3'], base['flow_iae_m3']))} "
                 f"(outlet errors include the total-flow error)")
    valves = ("valve_m_pct", "valve_f_pct", "valve_w_pct")
    if "travel" in md and "travel" in bd:
        tm, tb = sum(md["travel"][v] for v in valves), sum(bd["travel"][v] for v in valves)
        if tm > 2.0 * tb:
            parts.append(f"the MPC moves the outlet valves {tm:.1f} ranges in all against the baseline's {tb:.1f}")
    parts.extend(_common(mpc, md))
    return "; ".join(parts)


def _why_energy(mpc: Mapping, base: Mapping, md: Mapping, bd: Mapping) -> str:
    parts = []
    db, dh = mpc["blower_wh"] - base["blower_wh"], mpc["heater_wh"] - base["heater_wh"]
    parts.append(f"blower {mpc['blower_wh']:.2f} vs {base['blower_wh']:.2f} Wh ({db:+.2f}), "
                 f"heater {mpc['heater_wh']:.2f} vs {base['heater_wh']:.2f} Wh ({dh:+.2f})")
    if db > 0:
        parts.append(f"mean flow above reference by {md['flow_mean_excess_m3s'] * M3H:+.2f} m3/h "
                     f"(baseline {bd['flow_mean_excess_m3s'] * M3H:+.2f} m3/h); a more closed outlet "
                     "network needs more blower power for the same total flow")
    if dh > 0:
        parts.append(f"valve a at or above the trap threshold for {md['valve_a_saturated_s']:.0f} s "
                     f"(baseline {bd['valve_a_saturated_s']:.0f} s)")
    return "; ".join(parts)


def _common(mpc: Mapping, md: Mapping) -> list[str]:
    out = []
    if mpc["fallbacks"]:
        out.append(f"{mpc['fallbacks']} fallback steps ({md['fallbacks']['by_name']})")
    if mpc["violations_total"]:
        out.append(f"{mpc['violations_total']} constraint-violation samples")
    return out


def _t(x) -> str:
    return "not settled" if x is None else f"{x:.0f} s"


def _r(a, b):
    if a is None or b is None or b == 0:
        return None
    return a / b


def _flow_note(mpc: Mapping, base: Mapping, md: Mapping, bd: Mapping) -> str:
    """A caveat for a met criterion when the MPC tracks the total flow clearly worse than the baseline."""
    r = _r(mpc["flow_iae_m3"], base["flow_iae_m3"])
    if r is None or r <= FLOW_NOTE_RATIO:
        return ""
    return (f"met with a volume-flow IAE {r:.2f} x the baseline's (mean flow {md['flow_mean_excess_m3s'] * M3H:+.1f} "
            f"m3/h from its reference, baseline {bd['flow_mean_excess_m3s'] * M3H:+.1f} m3/h)")


def judge(kind: str, mpc: Mapping, base: Mapping, mpc_details: Mapping, base_details: Mapping) -> list[dict]:
    """Criteria of one scenario: list of ``{criterion, status ('met'/'not met'/'n/a'), ratio, value, why, note}``.

    ``note`` is a caveat on a met comparison (see :func:`_flow_note`), else empty.
    """
    out = _judge(kind, mpc, base, mpc_details, base_details)
    note = _flow_note(mpc, base, mpc_details, base_details)
    for c in out:
        c["note"] = note if (c["status"] == "met" and not c["criterion"].startswith("aim")) else ""
    return out


def _judge(kind: str, mpc: Mapping, base: Mapping, mpc_details: Mapping, base_details: Mapping) -> list[dict]:
    """The five criteria without notes (see :func:`judge`)."""
    out = []
    r_iae = _r(mpc["temp_iae_cs"], base["temp_iae_cs"])
    ok = r_iae is not None and r_iae < 1.0
    out.append({"criterion": "supply-temperature IAE below the baseline's", "status": "met" if ok else "not met",
                "ratio": r_iae, "value": f"{mpc['temp_iae_cs']:.1f} vs {base['temp_iae_cs']:.1f} C s",
                "why": "" if ok else _why_temperature(mpc, base, mpc_details, base_details)})
    if mpc["outlet_rms_m3s"] is None or base["outlet_rms_m3s"] is None:
        out.append({"criterion": "outlet-flow RMS error below the baseline's", "status": "n/a", "ratio": None,
                    "value": "no outlet split in the references", "why": ""})
    else:
        r = _r(mpc["outlet_rms_m3s"], base["outlet_rms_m3s"])
        ok = r is not None and r < 1.0
        out.append({"criterion": "outlet-flow RMS error below the baseline's", "status": "met" if ok else "not met",
                    "ratio": r,
                    "value": f"{mpc['outlet_rms_m3s'] * M3H:.2f} vs {base['outlet_rms_m3s'] * M3H:.2f} m3/h",
                    "why": "" if ok else _why_outlets(mpc, base, mpc_details, base_details)})
    r = _r(mpc["energy_wh"], base["energy_wh"])
    ok = r is not None and r <= 1.0
    out.append({"criterion": "electric energy (blower + heater) not above the baseline's",
                "status": "met" if ok else "not met", "ratio": r,
                "value": f"{mpc['energy_wh']:.2f} vs {base['energy_wh']:.2f} Wh",
                "why": "" if ok else _why_energy(mpc, base, mpc_details, base_details)})
    ok = r_iae is not None and r_iae <= IAE_AIM_RATIO
    out.append({"criterion": f"aim: temperature IAE at most {IAE_AIM_RATIO} x the baseline's",
                "status": "met" if ok else "not met", "ratio": r_iae, "value": _fmt_ratio(r_iae),
                "why": "" if ok else "; ".join(x for x in (f"ratio {_fmt_ratio(r_iae)}", _lag_floor(mpc, base),
                                                                  _why_temperature(mpc, base, mpc_details,
                                                                                   base_details)) if x)})
    steps = mpc_details["temperature_steps"]
    if kind != "cooling" or not steps:
        out.append({"criterion": f"aim: cooling steps within +-{TEMP_BAND_C} C in under {COOLING_TIME_AIM_S:.0f} s",
                    "status": "n/a", "ratio": None,
                    "value": "no cooling steps" if kind == "cooling" else "heating scenario", "why": ""})
    else:
        late = [s for s in steps if s["time_to_band_s"] is None or s["time_to_band_s"] >= COOLING_TIME_AIM_S]
        ok = not late
        worst = mpc["temp_time_to_band_max_s"]
        value = (f"max {_t(worst)} over {len(steps)} steps (baseline max "
                 f"{_t(base['temp_time_to_band_max_s'])}, {base['temp_unsettled']} unsettled)")
        if mpc["temp_unsettled"]:
            value += f", {mpc['temp_unsettled']} unsettled"
        why = "" if ok else "late: " + ", ".join(
            f"{s['from']:.1f}->{s['to']:.1f} C at {s['time_s']:.0f} s ({_t(s['time_to_band_s'])}, "
            f"response window {s['response_s']:.0f} s)" for s in late)
        out.append({"criterion": f"aim: cooling steps within +-{TEMP_BAND_C} C in under {COOLING_TIME_AIM_S:.0f} s",
                    "status": "met" if ok else "not met", "ratio": _r(worst, base["temp_time_to_band_max_s"]),
                    "value": value, "why": why})
    return out
