"""Soil-traverse environment throughput: env steps per second of the batched vector env on
the default 20 m x 10 m field (dx = 0.05 m), driving at 1 m/s on random arcs.

Keys: env_steps_per_s_n{1,16,64,256} with capped relaxation (4 updates per step), the step's
soil and observation in the fused numba kernels (`envs._step_numba`, sim.backend numba);
_n256_torch_relax with sim.backend torch: the whole step in torch ops with the torch
relaxation (the path CUDA runs); _n256_converged relaxed to convergence (fused kernels).
Each figure comes from a fresh process with OMP_WAIT_POLICY=PASSIVE: the OpenMP pools of
torch and numba then sleep instead of spinning, which on 2 shared cores is 3-10x faster
(and a fresh process does not inherit the thread pools of the benchmarks run before).
_n256_omp_spin is the same as _n256 with the OpenMP default (spinning) in this process.
env_steps_per_cpu_s_n{N}: the same runs per second of process CPU time (all threads), which
is less sensitive to other processes sharing the cores than the wall-clock figures."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def steps_per_second(num_envs: int, steps: int, blocks: int, sim: dict | None = None,
                     cpu: bool = False) -> float | tuple[float, float]:
    """Median over `blocks` of num_envs * steps / wall time, driving at 1 m/s on random arcs;
    with cpu=True also per second of process CPU time (all threads). sim: env.sim settings."""
    from envs.vector import SoilTraverseVectorEnv

    env = SoilTraverseVectorEnv(num_envs, {"sim": sim or {}})
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = np.stack([np.full((steps, num_envs), 1.0), rng.uniform(-0.3, 0.3, (steps, num_envs))],
                       axis=-1).astype(np.float32)
    for a in actions[:3]:
        env.step(a)
    rates, cpu_rates = [], []
    for _ in range(blocks):
        t0, c0 = time.perf_counter(), time.process_time()
        for a in actions:
            env.step(a)
        rates.append(num_envs * steps / (time.perf_counter() - t0))
        cpu_rates.append(num_envs * steps / (time.process_time() - c0))
    if cpu:
        return float(np.median(rates)), float(np.median(cpu_rates))
    return float(np.median(rates))


def _in_fresh_process(num_envs: int, steps: int, blocks: int, overrides: dict,
                      env: dict) -> tuple[float, float]:
    code = ("from torchsoil.bench.env import steps_per_second; "
            f"print(*steps_per_second({num_envs}, {steps}, {blocks}, {overrides!r}, cpu=True))")
    root = str(Path(__file__).resolve().parents[1])
    out = subprocess.run([sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": root, **env}, check=True,
                         capture_output=True, text=True)
    wall, cpu = out.stdout.strip().splitlines()[-1].split()
    return float(wall), float(cpu)


def run(quick: bool = False) -> dict[str, float]:
    steps, blocks = (8, 1) if quick else (25, 3)
    passive = {"OMP_WAIT_POLICY": "PASSIVE"}
    out: dict[str, float] = {}
    for n in (1, 16, 64, 256):
        wall, cpu = _in_fresh_process(n, steps, blocks, {"backend": "numba"}, passive)
        out[f"env_steps_per_s_n{n}"] = wall
        out[f"env_steps_per_cpu_s_n{n}"] = cpu
    out["env_steps_per_s_n256_torch_relax"] = _in_fresh_process(
        256, steps, blocks, {"backend": "torch"}, passive)[0]
    out["env_steps_per_s_n256_converged"] = _in_fresh_process(
        256, steps, blocks, {"backend": "numba", "fixed_iter": None}, passive)[0]
    out["env_steps_per_s_n256_omp_spin"] = steps_per_second(256, steps, blocks, {"backend": "numba"})
    return out
