"""Running the installed ``predictor`` as its own process and talking to it with rclpy.

``require_rclpy()`` at the top of a node test module: where rclpy cannot be imported the
module is skipped, except in CI (environment variable ``CI`` set), where that is a failure:
the node tests are never skipped there.

Every test process picks a private ``ROS_DOMAIN_ID`` (unless one is set) and localhost-only
discovery, inherited by the node processes it starts, so that test runs on one machine do
not see each other.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
import os
from pathlib import Path
import random
import shutil
import signal
import subprocess
import sys
import time
from typing import Any

import pytest
import yaml

os.environ.setdefault('ROS_DOMAIN_ID', str(random.SystemRandom().randint(1, 100)))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')


def require_rclpy() -> Any:
    """``import rclpy``; skip the module without it, fail in CI."""
    try:
        import rclpy
    except ImportError as err:
        if os.environ.get('CI'):
            raise RuntimeError(f'CI is set but rclpy cannot be imported ({err}): the node '
                               'tests must run in CI (pip install -e .[ros], .ci/run).'
                               ) from err
        pytest.skip(f'rclpy not importable ({err})', allow_module_level=True)
    return rclpy


def predictor_exe(name: str = 'predictor') -> str:
    """The installed ``predictor`` (or ``name``) entry point (the venv's, else PATH's)."""
    local = Path(sys.executable).parent / name
    found = str(local) if local.exists() else shutil.which(name)
    assert found, f'the {name} entry point is not installed (pip install -e .)'
    return found


class NodeProcess:
    """``predictor --ros-args --params-file P`` in its own process, output to a log file.

    Parameters
    ----------
    tmp_path : Path
        Where the params file and the log go.
    params : dict
        Node parameters (written to a params file, typed as given).
    name : str
        Node name (``__node:=``), also the log file's name.
    """

    def __init__(self, tmp_path: Path, params: dict[str, Any], name: str = 'predictor',
                 extra_args: tuple[str, ...] = (), exe: str = 'predictor') -> None:
        self.name = name
        self.params_file = tmp_path / f'{name}.yaml'
        self.params_file.write_text(yaml.safe_dump({'/**': {'ros__parameters': params}}),
                                    encoding='utf-8')
        self.log_path = tmp_path / f'{name}.log'
        self._log = self.log_path.open('wb')
        env = dict(os.environ, PYTHONUNBUFFERED='1', RCUTILS_COLORIZED_OUTPUT='0',
                   OPENBLAS_NUM_THREADS='1', OMP_NUM_THREADS='1')
        self.proc = subprocess.Popen(
            [predictor_exe(exe), '--ros-args', '-r', f'__node:={name}', '--params-file',
             str(self.params_file), *extra_args],
            stdout=self._log, stderr=subprocess.STDOUT, env=env)

    @property
    def fqn(self) -> str:
        """Fully qualified node name."""
        return f'/{self.name}'

    def log(self) -> str:
        """Everything the node printed so far."""
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(encoding='utf-8', errors='replace')

    def wait(self, timeout: float = 20.0) -> int:
        """Wait for the process to exit; its status."""
        try:
            return self.proc.wait(timeout)
        finally:
            self._log.close()

    def stop(self, sig: int = signal.SIGINT, timeout: float = 10.0) -> int:
        """Send ``sig`` and wait; the exit status."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        return self.wait(timeout)

    def kill(self) -> None:
        """Make sure the process is gone (test clean-up)."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        self._log.close()


_PAUSER = r"""
import os, signal, sys, time
pid = int(sys.argv[1])
print('ready', flush=True)
start, *plan = sys.stdin.readline().split()
for item in plan:
    at, length = map(float, item.split(':'))
    time.sleep(max(0.0, float(start) + at - time.monotonic()))
    os.kill(pid, signal.SIGSTOP)
    stopped = time.monotonic()
    time.sleep(length)
    os.kill(pid, signal.SIGCONT)
    print(f'{stopped - float(start):.4f} {time.monotonic() - stopped:.4f}', flush=True)
"""


class Pauser:
    """Stops a process (``SIGSTOP``) and resumes it on a schedule, from a process of its own.

    The pauses are timed on the system's monotonic clock by a small process that sleeps in
    between, not by the test process: a test process busy sending at 1 kHz is the one the
    scheduler holds back on a loaded machine, and a ``SIGCONT`` sent from its loop once came
    0.57 s late for a planned 150 ms pause (the node then met a longer pause than planned).

    Parameters
    ----------
    pid : int
        The process to pause.
    plan : dict
        Seconds after :meth:`start` -> seconds stopped.
    """

    def __init__(self, pid: int, plan: dict[float, float]) -> None:
        self.plan = dict(sorted(plan.items()))
        self.proc = subprocess.Popen([sys.executable, '-c', _PAUSER, str(pid)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def start(self, t0: float) -> None:
        """Time the plan from ``t0`` (``time.monotonic()``, the same clock in every process).

        Waits for the pauser's interpreter first; give ``t0`` after this returns.
        """
        assert self.proc.stdin is not None and self.proc.stdout is not None
        assert self.proc.stdout.readline().strip() == 'ready', 'the pauser did not start'
        self.proc.stdin.write(' '.join([f'{t0:.6f}'] + [f'{at}:{length}' for at, length
                                                        in self.plan.items()]) + '\n')
        self.proc.stdin.close()

    def done(self, timeout: float = 10.0) -> list[tuple[float, float]]:
        """Wait for the plan to end: each pause as it happened, (start after t0, length)."""
        assert self.proc.stdout is not None
        self.proc.wait(timeout)
        out = self.proc.stdout.read()
        return [(float(a), float(b)) for a, b in (line.split() for line in out.splitlines())]

    def kill(self) -> None:
        """Make sure the pauser is gone (test clean-up)."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


class Client:
    """A plain rclpy node in the test process, with its own context and executor."""

    def __init__(self, name: str = 'test_client') -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, cond: Callable[[], bool], timeout: float = 10.0) -> bool:
        """Spin until ``cond()`` is true or ``timeout`` seconds passed; the last ``cond()``."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if cond():
                return True
            self.executor.spin_once(timeout_sec=0.01)
        return cond()

    def spin_for(self, seconds: float) -> None:
        """Spin for ``seconds``."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.01)

    def call(self, srv_type: Any, name: str, request: Any, timeout: float = 10.0, *,
             idempotent: bool = False) -> Any:
        """Call a service; its response (asserts that it answered).

        The service being found does not mean that its response reaches this client yet:
        a response sent before the server's writer has matched the client's reader is lost
        (the first ``get_state`` of a node just started went unanswered for 10 s in one
        clean-clone CI run). An ``idempotent`` request is sent again every 2 s until answered.
        """
        client = self.node.create_client(srv_type, name)
        try:
            assert client.wait_for_service(timeout_sec=timeout), f'no service {name}'
            end = time.monotonic() + timeout
            future = client.call_async(request)
            while True:
                left = end - time.monotonic()
                self.executor.spin_until_future_complete(
                    future, timeout_sec=min(2.0, left) if idempotent else left)
                if future.done() or not idempotent or time.monotonic() >= end:
                    break
                future = client.call_async(request)
            assert future.done(), f'{name} did not answer'
            return future.result()
        finally:
            self.node.destroy_client(client)

    def set_parameters(self, node: str, **values: Any) -> list[Any]:
        """``ros2 param set`` through the parameter service; the SetParametersResult list."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        request = SetParameters.Request(parameters=[
            Parameter(k, value=v).to_parameter_msg() for k, v in values.items()])
        return list(self.call(SetParameters, f'{node}/set_parameters', request).results)

    def close(self) -> None:
        """Destroy the node and shut the context down."""
        import rclpy

        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def client_fixture(name: str = 'test_client') -> Any:
    """A pytest fixture ``client``: a :class:`Client` named ``name`` for one test, closed after.

    In a test module: ``client = client_fixture('my_client')``.
    """
    @pytest.fixture
    def client() -> Iterator[Client]:
        c = Client(name)
        yield c
        c.close()
    return client


def no_noise(log: str) -> list[str]:
    """Lines of a node log that must never appear (tracebacks, publish/context errors)."""
    bad = ('Traceback', 'Failed to publish', 'context is invalid', 'context is not valid',
           'RCLError', 'Exception')
    return [line for line in log.splitlines() if any(b in line for b in bad)]
