"""Real measurements of the thesis used to check the valve network (thesis sections 4.5.2 and 5.3).

Tables 3-5: with one outlet valve moved and the other two closed, the total volume flow
V (m3/s) and the pressure loss dp (Pa) of the whole network; R = dp / V^2 (kg/m^7) is the
network resistance at that angle (thesis sec. 3.2, 4.5.2).

Table 6: thirteen settings of the outlet valves (columns alpha, beta, gamma are the angles of
valves m, f, w in % of servo travel), the measured total flow V (m3/s) and the mean air
velocities (m/s) at the outlets mm (middle panel) and mf (side window), both fed by valve m,
f (feet), and wd (defrost) and ww (windshield), both fed by valve w (thesis sec. 5.3).

Outlet areas (cm^2, order mm, mf, f, wd, ww): ``A_M_CM2`` measured, ``A_C_CM2`` computed by
the thesis from table 6 with S A = V / 2 (perfect left/right symmetry: the velocities were
measured on one side, so one side carries half the total flow; thesis sec. 5.3).
"""

from __future__ import annotations

import numpy as np

#: Thesis table 3: valve m angle (%), V (m3/s), dp (Pa); valves f and w closed.
TABLE_3_M = (
    (0, 0.02833, 186), (10, 0.02861, 186), (20, 0.02861, 184), (30, 0.02889, 182), (40, 0.02972, 172),
    (50, 0.03833, 236), (60, 0.04194, 182), (70, 0.04583, 137), (80, 0.04944, 87), (90, 0.05111, 59),
    (100, 0.05167, 44))
#: Thesis table 4: valve f angle (%), V (m3/s), dp (Pa); valves m and w closed.
TABLE_4_F = (
    (0, 0.02778, 178), (3, 0.02778, 179), (6, 0.02806, 176), (9, 0.02833, 177), (12, 0.02833, 176),
    (15, 0.02889, 167), (18, 0.03667, 232), (21, 0.03778, 220), (24, 0.04000, 190), (27, 0.04444, 133),
    (30, 0.04472, 113), (40, 0.04528, 83), (50, 0.04833, 57), (60, 0.05000, 37), (70, 0.05000, 38),
    (80, 0.05056, 36), (90, 0.05056, 35), (100, 0.05139, 30))
#: Thesis table 5: valve w angle (%), V (m3/s), dp (Pa); valves m and f closed.
TABLE_5_W = (
    (0, 0.02833, 173), (10, 0.02833, 170), (14, 0.02833, 170), (18, 0.02889, 170), (22, 0.03861, 217),
    (26, 0.04083, 181), (30, 0.04306, 159), (40, 0.04667, 122), (50, 0.04917, 77), (60, 0.05056, 52),
    (70, 0.05139, 40), (80, 0.05167, 35), (90, 0.05194, 30), (100, 0.05194, 31))

#: Which valve each of tables 3-5 moves (the other two are closed).
NETWORK_TABLES = {"m": TABLE_3_M, "f": TABLE_4_F, "w": TABLE_5_W}

#: Thesis table 6 columns.
TABLE_6_COLUMNS = ("valve_m_pct", "valve_f_pct", "valve_w_pct", "volume_flow_m3s",
                   "v_mm_ms", "v_mf_ms", "v_f_ms", "v_wd_ms", "v_ww_ms")
#: Thesis table 6 (alpha = m, beta = f, gamma = w).
TABLE_6 = (
    (100, 0, 0, 0.0547, 3.03, 5.78, 1.03, 0.18, 0.40),
    (100, 100, 0, 0.0572, 2.21, 4.24, 3.58, 0.04, 0.31),
    (0, 100, 0, 0.0539, 0.97, 1.16, 6.58, 0.14, 0.36),
    (0, 100, 100, 0.0569, 0.64, 0.56, 3.56, 2.08, 4.71),
    (0, 0, 100, 0.0542, 0.82, 0.88, 1.16, 2.37, 6.03),
    (50.11, 21.84, 21.87, 0.0433, 1.29, 2.91, 2.10, 0.53, 1.68),
    (63.98, 26, 32.11, 0.0517, 1.48, 4.00, 1.58, 2.71, 1.28),
    (51.11, 21.84, 100, 0.0556, 0.75, 1.89, 1.30, 6.18, 2.47),
    (100, 21.84, 21.87, 0.0558, 3.19, 5.43, 1.41, 0.42, 1.33),
    (50.11, 100, 21.87, 0.0553, 0.98, 1.94, 5.42, 0.38, 1.26),
    (63.98, 21.84, 0, 0.0464, 1.64, 4.40, 2.13, 0.15, 0.38),
    (0, 26, 21.87, 0.0328, 1.31, 1.49, 2.22, 0.40, 1.93),
    (50.11, 0, 32.11, 0.0389, 0.95, 2.17, 1.40, 1.13, 2.49))

#: Outlet order of the velocity columns and of the area vectors.
OUTLETS = ("mm", "mf", "f", "wd", "ww")
#: Branch (valve) feeding each outlet (thesis sec. 4.5.2, fig. 38).
OUTLET_BRANCH = {"mm": "m", "mf": "m", "f": "f", "wd": "w", "ww": "w"}
#: Measured outlet areas A_m in cm^2 (thesis sec. 5.3).
A_M_CM2 = (32.81, 32.81, 34.59, 8.0, 25.9)
#: Outlet areas A_c in cm^2 computed by the thesis from table 6 (thesis sec. 5.3).
A_C_CM2 = (12.13, 30.6, 31.31, 17.55, 23.88)
#: Factor from one side's outlet flow to the branch total (thesis sec. 5.3: perfect symmetry).
SYMMETRY_FACTOR = 2.0


def network_rows() -> dict[str, np.ndarray]:
    """Tables 3-5 as arrays: ``angles_pct`` (n x 3, m f w), ``flow_m3s``, ``dp_pa``, ``r_kg_m7``, ``valve``."""
    angles, flow, dp, valve = [], [], [], []
    for i, (name, table) in enumerate(NETWORK_TABLES.items()):
        for a, v, p in table:
            row = [0.0, 0.0, 0.0]
            row[i] = float(a)
            angles.append(row)
            flow.append(v)
            dp.append(p)
            valve.append(name)
    flow_a = np.array(flow, float)
    dp_a = np.array(dp, float)
    return {"angles_pct": np.array(angles), "flow_m3s": flow_a, "dp_pa": dp_a,
            "r_kg_m7": dp_a / flow_a ** 2, "valve": np.array(valve)}


def table6() -> dict[str, np.ndarray]:
    """Table 6 as arrays: ``angles_pct`` (13 x 3, m f w), ``flow_m3s`` (13), ``velocity_ms`` (13 x 5)."""
    t = np.array(TABLE_6, float)
    return {"angles_pct": t[:, 0:3], "flow_m3s": t[:, 3], "velocity_ms": t[:, 4:9]}


def branch_flows_m3s(velocity_ms: np.ndarray, areas_cm2) -> np.ndarray:
    """Branch flows (m, f, w) in m3/s from outlet velocities and areas, with the symmetry factor 2."""
    per_outlet = SYMMETRY_FACTOR * np.atleast_2d(velocity_ms) * np.asarray(areas_cm2, float) * 1e-4
    cols = {b: [i for i, o in enumerate(OUTLETS) if OUTLET_BRANCH[o] == b] for b in ("m", "f", "w")}
    return np.stack([per_outlet[:, cols[b]].sum(axis=1) for b in ("m", "f", "w")], axis=1)


def computed_areas_cm2(rows=None) -> np.ndarray:
    """Outlet areas from S A = V / 2 by least squares (the thesis's A_c when all rows are used)."""
    t = table6()
    idx = np.arange(len(t["flow_m3s"])) if rows is None else np.asarray(rows)
    sol, *_ = np.linalg.lstsq(t["velocity_ms"][idx], t["flow_m3s"][idx] / SYMMETRY_FACTOR, rcond=None)
    return sol * 1e4
