"""Controllers for the HVAC box: the MPC, its estimator, the thesis baseline, and the daemon."""
