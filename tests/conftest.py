"""Shared fixtures: free loopback ports and process cleanup."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def hub() -> str:
    """A free loopback endpoint for a test's Zenoh hub."""
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def procs():
    """Start ``python -m ...`` processes; every one is killed and reaped at teardown."""
    started: list[subprocess.Popen] = []

    def start(*args: str, **kw) -> subprocess.Popen:
        p = subprocess.Popen([sys.executable, "-m", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, start_new_session=True, **kw)
        started.append(p)
        return p

    yield start
    for p in started:
        if p.poll() is None:
            p.kill()
        p.communicate()
