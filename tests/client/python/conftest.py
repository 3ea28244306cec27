"""Fixtures of the kdrt Python client tests: a real kdrt-server on an ephemeral loopback port,
the kdrt CLI (the C++ client) to compare answers with, and the test meshes.

ctest (tests/client/CMakeLists.txt, test client_python) runs these with Debian's /usr/bin/python3
and sets KDRT_SERVER_BINARY, KDRT_CLI_BINARY, KDRT_TEST_DATA_DIR and PYTHONPATH (client/python).
"""

import os
import shutil
import subprocess
import tempfile
import time
import urllib.request

import pytest

import kdrt


def _env(name):
    value = os.environ.get(name)
    if not value:
        pytest.exit(f"{name} is not set (run these tests through ctest -R client_python)", 2)
    return value


class Server:
    """A kdrt-server process; stopped (SIGTERM, then waited for) by stop()."""

    def __init__(self, *extra):
        self.dir = tempfile.mkdtemp(prefix="kdrt-py-test-")
        port_file = os.path.join(self.dir, "port")
        self.log_path = os.path.join(self.dir, "server.log")
        self.log = open(self.log_path, "wb")
        self.process = subprocess.Popen(
            [_env("KDRT_SERVER_BINARY"), "--listen", "127.0.0.1:0", "--port-file", port_file,
             "--cache-dir", os.path.join(self.dir, "cache"), "--threads", "2",
             "--log-level", "warn", *extra],
            stdout=self.log, stderr=subprocess.STDOUT)
        self.port = None
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"kdrt-server exited with {self.process.returncode}: "
                                   f"{open(self.log_path).read()}")
            try:
                with open(port_file) as f:
                    text = f.read().strip()
                if text:
                    self.port = int(text)
                    with urllib.request.urlopen(f"{self.url}/readyz", timeout=5) as answer:
                        if answer.status == 200:
                            return
            except (OSError, ValueError):
                pass
            time.sleep(0.02)
        self.stop()
        raise RuntimeError("kdrt-server did not become ready within 60 s")

    @property
    def url(self):
        return f"http://127.0.0.1:{self.port}"

    def stop(self):
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.log.close()
        shutil.rmtree(self.dir, ignore_errors=True)


@pytest.fixture(scope="session")
def server():
    s = Server()
    yield s
    s.stop()


@pytest.fixture(scope="session")
def data_dir():
    return _env("KDRT_TEST_DATA_DIR")


@pytest.fixture(scope="session")
def cli():
    """Runs the kdrt CLI (the C++ client) and returns its completed process."""
    binary = _env("KDRT_CLI_BINARY")

    def run(*args, check=True):
        done = subprocess.run([binary, *args], capture_output=True, text=True, timeout=300)
        if check and done.returncode != 0:
            raise AssertionError(f"kdrt {' '.join(args)} exited with {done.returncode}: "
                                 f"{done.stdout}{done.stderr}")
        return done
    return run


@pytest.fixture()
def client(server):
    with kdrt.Client(server.url, max_retries=2, backoff_initial=0.01) as c:
        yield c


@pytest.fixture(scope="session")
def bunny(server, data_dir):
    with kdrt.Client(server.url) as c:
        return c.upload(os.path.join(data_dir, "bunny00.off"))
