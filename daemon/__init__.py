"""The controller daemon: the MPC (or the thesis baseline) running for real, safe under faults.

Run it with ``hvac-mpc daemon --config daemon.toml`` (``--example-config`` prints a commented
configuration; docs/real-box.md describes it). Modules, one job each:

* :mod:`.config`      the TOML configuration, validated key by key;
* :mod:`.loop`        the fixed-rate loop, shutdown sequence and log (:class:`.loop.Daemon`);
* :mod:`.safety`      sensor checks, heater interlock, heater temperature estimate, safe command;
* :mod:`.controllers` controllers by name, the deadline-guarded fallback chain, fault injection;
* :mod:`.backends`    the I/O interface, the simulated plant backend, fault injection;
* :mod:`.modbus`      the Modbus TCP register map and client backend; :mod:`.modbus_sim` the
  simulated plant behind a real Modbus TCP server;
* :mod:`.api`         the HTTP/JSON reference API;
* :mod:`.io`          the backend interface (:class:`.io.IoBackend`, :class:`.io.BackendError`);
* :mod:`.soak`        the soak run (the fault campaign is :mod:`hvac_mpc.benchmarks.daemon_campaign`);
* :mod:`.main`        the ``daemon`` subcommand.
"""
