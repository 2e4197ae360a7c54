"""Localhost JAX clusters for tests: a free port and N processes run to the end."""

from __future__ import annotations

import os
import socket
import subprocess


def free_port() -> int:
    """A TCP port of 127.0.0.1 free now (the coordinator's)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def run_processes(
    commands: list[list[str]], env: dict | None = None, timeout_s: float = 240
) -> tuple[list[str], list[str]]:
    """Start every command at once (the processes of one cluster), wait for all.

    Returns:
        ``(stdouts, errors)``: each process's stdout, and one message per process
        that timed out (every process is then killed) or exited non-zero, with its
        stderr; no error: every process exited 0.
    """
    env = {**os.environ, "JAX_PLATFORMS": "cpu", **(env or {})}
    procs = [
        subprocess.Popen(
            cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        for cmd in commands
    ]
    stdouts, errors = [], []
    for i, proc in enumerate(procs):
        try:
            stdout, stderr = proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            for other in procs:
                other.kill()
            stdout, stderr = proc.communicate()
            errors.append(f"process {i} timed out after {timeout_s} s:\n{stderr}")
        else:
            if proc.returncode != 0:
                errors.append(f"process {i} exited {proc.returncode}:\n{stderr}")
        stdouts.append(stdout)
    return stdouts, errors
