"""Runs kdrt-server as systemd's Type=notify would (daemon_install_test.cmake): a datagram socket
in $NOTIFY_SOCKET, READY=1 awaited before the service counts as started, then `kdrt health`
against it, SIGTERM, STOPPING=1 and exit status 0.

    notify_run.py SERVER CONFIG KDRT WORK_DIR
"""
import json
import os
import signal
import socket
import subprocess
import sys

server, config, kdrt, work = sys.argv[1:5]
sock_path = os.path.join(work, "notify.sock")
sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
sock.bind(sock_path)
sock.settimeout(60)
port_file = os.path.join(work, "port")
log = open(os.path.join(work, "server.log"), "wb")
proc = subprocess.Popen(
    [server, "--config", config, "--listen", "127.0.0.1:0", "--port-file", port_file,
     "--cache-dir", os.path.join(work, "store")],
    stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ, NOTIFY_SOCKET=sock_path))


def fail(message):
    proc.kill()
    proc.wait()
    log.close()
    sys.exit(message + "\n" + open(os.path.join(work, "server.log")).read())


try:
    ready = sock.recv(4096).decode()
except socket.timeout:
    fail("no datagram on NOTIFY_SOCKET within 60 s")
if not ready.startswith("READY=1\n") or "STATUS=ready, 0 meshes" not in ready:
    fail("the first notice is not READY=1 with the status: %r" % ready)
port = open(port_file).read().strip()
health = subprocess.run([kdrt, "health", "--json", "--server", "http://127.0.0.1:" + port,
                         "--retries", "0"], capture_output=True, text=True)
if health.returncode != 0 or json.loads(health.stdout)["ready"] is not True:
    fail("kdrt health after READY=1: exit %d %s %s" % (health.returncode, health.stdout,
                                                        health.stderr))
proc.send_signal(signal.SIGTERM)
try:
    stopping = sock.recv(4096).decode()
except socket.timeout:
    fail("no STOPPING=1 after SIGTERM")
if not stopping.startswith("STOPPING=1\n"):
    fail("the notice after SIGTERM is not STOPPING=1: %r" % stopping)
if proc.wait(timeout=60) != 0:
    fail("kdrt-server exited with %d after SIGTERM" % proc.returncode)
print("READY=1 then STOPPING=1; kdrt health: " + health.stdout.strip())
