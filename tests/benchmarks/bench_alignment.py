"""Benchmark: fine alignment time (simulated) and Modbus round-trip latency on loopback.

Run: ``python tests/benchmarks/bench_alignment.py``

* Fine alignment from a 200 um / 300 urad start must converge in <= 5 s of
  simulated time (the issue's target), over seeds and CNC positions whose
  beams go from nearly level to steep and from 0.7 m to 2 m long; the first
  distance guess is a blind 1000 mm.
* Round-trip latency of one Modbus holding-register read (6 registers) from
  the driver's transport to the simulated unit's Modbus TCP server on 127.0.0.1.
"""

from __future__ import annotations

import socket
import sys
import time

import numpy as np

from firmware_iface.modbus import tcp_transport
from sim.clock import SimClock
from sim.servers.modbus import ModbusUnitServer
from sim.units import SimUnit
from xmalign.alignment import fine_align
from xmalign.cli.align import simulated_setup
from xmalign.machine import default_machine_path, load_machine

TARGET_S = 5.0
POSITIONS = (
    [1600, 1050, -100],
    [300, 1400, -400],
    [1900, 200, 0],
    [1000, 750, -250],
    [200, 150, -50],
)


def bench_fine_alignment(seeds: range = range(8)) -> bool:
    machine = load_machine(default_machine_path())
    times, steps, distances = [], [], []
    for seed in seeds:
        for position in POSITIONS:
            _, devices = simulated_setup(
                machine, np.array(position, dtype=float), seed, 200.0, 300.0
            )
            distances.append(devices.distance_mm)
            result = fine_align(
                devices.launch,
                devices.receiver,
                devices.interferometer,
                devices.clock,
                distance_mm=1000.0,
            )
            times.append(result.elapsed_s)
            steps.append(len(result.steps))
    times_s = np.array(times)
    print(
        f"fine alignment, {len(times)} runs (distances {min(distances):.0f}-"
        f"{max(distances):.0f} mm), simulated time to converge: median {np.median(times_s):.3f}"
        f" s, max {times_s.max():.3f} s (target <= {TARGET_S:g} s); steps median "
        f"{np.median(steps):.0f}, max {max(steps)}"
    )
    return bool(times_s.max() <= TARGET_S)


def bench_modbus_latency(n: int = 2000) -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = ModbusUnitServer(SimUnit("launch", SimClock(real_time=True)), "127.0.0.1", port)
    server.start()
    transport = tcp_transport("127.0.0.1", port, "launch unit")
    try:
        transport.read_registers(0, 6)
        latencies = []
        for _ in range(n):
            start = time.perf_counter()
            transport.read_registers(16, 6)
            latencies.append(time.perf_counter() - start)
    finally:
        transport.close()
        server.stop()
    ms = np.array(latencies) * 1e3
    print(
        f"Modbus TCP read of 6 registers on loopback, {n} reads: median {np.median(ms):.3f} ms,"
        f" p95 {np.percentile(ms, 95):.3f} ms, max {ms.max():.3f} ms"
    )


if __name__ == "__main__":
    ok = bench_fine_alignment()
    bench_modbus_latency()
    sys.exit(0 if ok else 1)
