"""Numbers of the independent box: thesis values with their section, assumptions marked ASSUMPTION.

Units are in the names (W, degC, s, m3/s, kg/s, Pa, kg/m7 for flow resistances dp = R V^2).
Everything here is an immutable constant; nothing is imported from ``hvac_mpc.models``.
"""

from __future__ import annotations

# ---------------------------------------------------------------- actuators (thesis 2.1, 2.3; docs/model.md sec. 2)
BLOWER_MIN_W = 30.0          # docs/model.md sec. 2: P_b in [30, 300] W
BLOWER_MAX_W = 300.0         # thesis 2.1: 20 A at 15 V, "about 300 W"
HEATER_MAX_W = 240.0         # thesis 2.3: "a maximum of about 240 W at low temperatures"
VALVE_MIN_PCT = 0.0          # thesis 2.5 / table 1: servo travel in %
VALVE_MAX_PCT = 100.0

# ---------------------------------------------------------------- air (thesis 4, 4.4)
RHO_SLOPE = -0.004395        # thesis 4: rho(T) = -0.004395 T + 1.23 (kg/m3, T in degC)
RHO_OFFSET = 1.23
CP_AIR = 1007.0              # thesis 4.4: c_pa in J/(kg K)

# ---------------------------------------------------------------- blower (thesis 4.1)
MOTOR_TAU_S = 268.0          # thesis 4.1.1: tau_m = 268 s
MOTOR_GAIN_FULL_C = 2.4      # ASSUMPTION (docs/model.md sec. 1): K_m = 2.4 (P_b/300)^1.5 degC (">2 C", thesis 4.1.1)
MOTOR_GAIN_EXPONENT = 1.5    # ASSUMPTION (docs/model.md sec. 1)
BLOWER_FLOW_PER_W = 1.9e-4   # ASSUMPTION (docs/model.md sec. 1): V = 1.9e-4 P_b m3/s, all valves open, full bypass

# ---------------------------------------------------------------- bypass valve a (thesis 4.5.1)
BYPASS_MAX = 0.9             # thesis 4.5.1: at least 10 % of the air always crosses the core
BYPASS_EXPONENT = 1.3        # ASSUMPTION (docs/model.md sec. 1): b(a) = 0.9 (1 - a/100)^1.3
BYPASS_FLOW_REF_KGS = 0.04   # ASSUMPTION: mass flow at which a flow-dependent split equals b(a) (Variant.bypass_flow_exponent)
CORE_FLOW_RATIO = 0.9        # thesis 4.5.1: ~10 % less flow when all air crosses the core

# ---------------------------------------------------------------- chiller and cooler core (thesis 2.2, 4.2)
CHILLER_RISE_C_PER_S = 0.00702   # thesis 4.2: rising ramp
CHILLER_FALL_C_PER_S = 0.00682   # thesis 4.2: falling ramp (mean of both: 0.00692)
CHILLER_BAND_C = 1.0             # ASSUMPTION (docs/model.md sec. 1): two-point control +-1 C around the set point
COOLER_SLOPE = 0.7564            # thesis 4.2: T_a = 0.7564 T_w + 6.312
COOLER_OFFSET_C = 6.312          # thesis 4.2
COOLER_NTU_REF_KGS = 0.03        # ASSUMPTION: core mass flow at which Variant.cooler_ntu holds
COOLER_NTU_EXPONENT = 0.4        # ASSUMPTION: NTU ~ (core mass flow)^-0.4 (air-side film coefficient ~ m^0.6)

# ---------------------------------------------------------------- heater (thesis 4.3, 4.4; 2.3)
HEATER_MASS_KG = 0.243           # thesis 4.4: m_h = 243 g
HEATER_CP = 897.0                # thesis 4.4: c_h, aluminium
HEATER_KA_W_PER_K = 2.49         # thesis 4.4: k_A,h = 2.49 W/K
HEATER_KP = 0.669                # thesis 4.4: share of the electric power dissipated in the heater
PTC_KNEE_C = 60.0                # ASSUMPTION (docs/model.md sec. 1, thesis 2.3 fig. 12): full power below ~60 C
PTC_ZERO_C = 165.0               # thesis 2.3: temperature limited at ~165 C (power falls to 0 there)

# ---------------------------------------------------------------- sensors (thesis 2.4, 5.4.1)
THERMOCOUPLE_TAU_S = 5.73        # thesis 5.4.1: tau_TC = 5.73 s (sensor and mixing)
FLOW_SENSOR_C = 0.0097           # thesis 2.4: V = C sqrt(dp) sqrt(1.2/rho), C in m3/s per sqrt(Pa)
FLOW_SENSOR_RHO_REF = 1.2        # thesis 2.4
NOISE_SUPPLY_C = 0.05            # ASSUMPTION: thermocouple noise (std, degC)
NOISE_FLOW_M3S = 2e-4            # ASSUMPTION: volume-flow sensor noise (std)
NOISE_INLET_C = 0.05             # ASSUMPTION: inlet temperature noise (std)
NOISE_OTHER_C = 0.05             # ASSUMPTION: water, heater outlet and cabin thermocouples as the supply one

# ---------------------------------------------------------------- environment defaults
CABIN_TEMP_C = 24.0              # ASSUMPTION: cabin air around the duct
SUBSTEP_S = 0.25                 # integration substep (s); every update is an exact or implicit solution

# ---------------------------------------------------------------- valve network tables (thesis 4.5.2)
# (angle %, network resistance R kg/m7) measured with the other two valves closed.
TABLE3_RM = ((0, 231696), (10, 227218), (20, 224775), (30, 218077), (40, 194700), (50, 160605),
             (60, 103448), (70, 65217), (80, 35586), (90, 22585), (100, 16483))
TABLE4_RF = ((0, 230688), (3, 231984), (6, 223602), (9, 220484), (12, 219239), (15, 200104),
             (18, 172562), (21, 154152), (24, 118750), (27, 67331), (30, 56498), (40, 40486),
             (50, 24400), (60, 14800), (70, 15200), (80, 14085), (90, 13694), (100, 11360))
TABLE5_RW = ((0, 215502), (10, 211765), (14, 211765), (18, 203698), (22, 145558), (26, 108555),
             (30, 85771), (40, 56020), (50, 31853), (60, 20345), (70, 15147), (80, 13111),
             (90, 11118), (100, 11489))
# Measured volume flow (m3/s) of the same rows, one blower setting: they give the blower's stiffness.
TABLE3_FLOW = (0.02833, 0.02861, 0.02861, 0.02889, 0.02972, 0.03833, 0.04194, 0.04583, 0.04944,
               0.05111, 0.05167)
TABLE4_FLOW = (0.02778, 0.02778, 0.02806, 0.02833, 0.02833, 0.02889, 0.03667, 0.03778, 0.04000,
               0.04444, 0.04472, 0.04528, 0.04833, 0.05000, 0.05000, 0.05056, 0.05056, 0.05139)
TABLE5_FLOW = (0.02833, 0.02833, 0.02833, 0.02889, 0.03861, 0.04083, 0.04306, 0.04667, 0.04917,
               0.05056, 0.05139, 0.05167, 0.05194, 0.05194)
