"""Helpers of the multi-device tests (a uniquely named module, not a conftest, so it never
clashes with a package's conftest): running a JAX job in a fresh process with a fixed number
of CPU devices (the device count is read once, when JAX starts, so it cannot change inside
this pytest process)."""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def device_env(devices: int) -> dict:
    """This process's environment with ``devices`` forced host (CPU) devices and the CPU
    platform chosen (so a GPU machine runs the same CPU comparison)."""
    env = dict(os.environ)
    flags = re.sub(r"--xla_force_host_platform_device_count=\S+", "",
                   env.get("XLA_FLAGS", ""))
    env["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={devices}".strip()
    env["JAX_PLATFORMS"] = "cpu"
    return env


def run_all(jobs: list[tuple[list[str], int]], timeout: float, cwd=None) -> list[str]:
    """Run every ``(args, devices)`` job (``python *args`` with ``devices`` CPU devices, in
    directory ``cwd``) at the same time (XLA compiles mostly on one core) and return their
    stdouts; fail the test with every job's output if one exits non-zero or they run past
    ``timeout`` seconds (all are killed then)."""
    procs = [subprocess.Popen([sys.executable, *args], env=device_env(devices), cwd=cwd,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for args, devices in jobs]
    outputs = []
    try:
        for proc in procs:
            outputs.append(proc.communicate(timeout=timeout))
    except subprocess.TimeoutExpired:
        for proc in procs:
            proc.kill()
        outputs = [proc.communicate() for proc in procs]
        raise AssertionError(f"jobs ran past {timeout} s:\n" + _report(jobs, procs, outputs)
                             ) from None
    if any(proc.returncode != 0 for proc in procs):
        raise AssertionError("a job failed:\n" + _report(jobs, procs, outputs))
    return [out for out, _ in outputs]


def _report(jobs, procs, outputs) -> str:
    return "\n".join(f"--- {args} ({devices} devices), exit {proc.returncode}:\n{out}\n"
                     f"{err[-3000:]}"
                     for (args, devices), proc, (out, err) in zip(jobs, procs, outputs,
                                                                  strict=True))


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
