#!/usr/bin/env python3
"""What nginx (docker/nginx/ routing) adds in front of kdrt-server, on loopback.

Starts one kdrt-server (replica r0) and nginx in front of it, uploads tests/data/bunny00.off, then
measures the same requests direct and through nginx, interleaved (A, B, A, B, ...) so drift and
noise hit both alike:
  - latency p50/p99 of 1-ray and 1000-ray KDRR batches (keep-alive connections);
  - throughput of 1M-ray batches (a 32 MiB body, a 16 MiB answer), median of --reps.
Prints one line per measurement. Usage (after a Release build):
  python3 tests/bench/nginx_overhead.py [--build build/release] [--requests 2000] [--reps 5]

With --split-render N it measures a frame instead (docs/scale-out.md, "Fan-out of one frame"):
--replicas (3) servers sharing one store behind nginx, the bunny rendered at --size (eyelight),
interleaved, --reps times each:
  - direct: one synchronous PNG render asked of one replica (the server renders and encodes);
  - split CLI: `kdrt render --split N` through nginx (the whole command: N raw bands, stitched
    and encoded by the CLI, process start included); its file must equal the direct PNG;
  - kdrt --help: the CLI's start-up alone (process, dynamic libraries), part of split CLI;
  - raw direct / raw split: the frame's float pixels (KDRI) in one request to one replica, and
    as N bands (`?route=<id>.<k>`) sent at once through nginx: the transport and fan-out alone.
  python3 tests/bench/nginx_overhead.py --split-render 6 [--replicas 3] [--size 1024x768] [--reps 20]
"""
import argparse
import http.client
import json
import os
import pathlib
import random
import shutil
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time

ROOT = pathlib.Path(__file__).resolve().parents[2]


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_http(port, path="/readyz", timeout=30):
    deadline = time.time() + timeout
    while time.time() < deadline:
        try:
            c = http.client.HTTPConnection("127.0.0.1", port, timeout=1)
            c.request("GET", path)
            if c.getresponse().status == 200:
                return
        except OSError:
            pass
        time.sleep(0.05)
    raise RuntimeError(f"nothing answers {path} on port {port}")


def rays_body(count, seed):
    rng = random.Random(seed)
    out = bytearray(b"KDRR" + struct.pack("<HHII", 1, 0, count, 0))
    for _ in range(count):
        # From a sphere around the bunny (bounds about [-0.1, 0.1]^3) towards its middle.
        o = [rng.uniform(-1, 1) for _ in range(3)]
        d = [-c + rng.uniform(-0.05, 0.05) for c in o]
        out += struct.pack("<8f", o[0], o[1], o[2], 0.0, d[0], d[1], d[2], float("inf"))
    return bytes(out)


def post(conn, path, body):
    conn.request("POST", path, body, {"Content-Type": "application/x-kdrt-rays"})
    res = conn.getresponse()
    data = res.read()
    if res.status != 200:
        raise RuntimeError(f"{path}: {res.status} {data[:200]!r}")
    return data


def nginx_conf(tmp, nport, replicas):
    """nginx.conf with the shipped routing in front of `replicas`: [(name, port), ...]."""
    servers = "".join(f" server 127.0.0.1:{port};" for _, port in replicas)
    per_replica = "".join(
        f"    upstream kdrt_replica_{name} {{ server 127.0.0.1:{port}; keepalive 4; "
        f"keepalive_timeout 1s; }}\n" for name, port in replicas)
    job_map = "".join(f" {name} kdrt_replica_{name};" for name, _ in replicas)
    return f"""{'user root;' if os.geteuid() == 0 else ''}
daemon off;
worker_processes 1;
pid {tmp}/nginx.pid;
error_log {tmp}/nginx.log warn;
events {{ worker_connections 1024; }}
http {{
    access_log off;
    client_body_temp_path {tmp}/body;
    proxy_temp_path {tmp}/proxy;
    include {ROOT}/docker/nginx/kdrt-http.conf;
    upstream kdrt_mesh {{ hash $kdrt_route_key consistent;{servers} keepalive 16; keepalive_timeout 1s; }}
    upstream kdrt_any {{ least_conn;{servers} keepalive 16; keepalive_timeout 1s; }}
{per_replica}    map $kdrt_job_replica $kdrt_job_upstream {{ default kdrt_any;{job_map} }}
    server {{ listen 127.0.0.1:{nport}; include {ROOT}/docker/nginx/kdrt-locations.conf; }}
}}
"""


def start_stack(server_bin, tmp, replica_count, procs):
    """kdrt-server replicas r0.. sharing tmp/store, and nginx in front; returns (ports, nport)."""
    ports = []
    for r in range(replica_count):
        port = free_port()
        procs.append(subprocess.Popen(
            [str(server_bin), "--listen", f"127.0.0.1:{port}", "--cache-dir", str(tmp / "store"),
             "--replica", f"r{r}", "--log-level", "warn"],
            stderr=open(tmp / f"server{r}.log", "w")))
        wait_http(port)
        ports.append(port)
    nport = free_port()
    (tmp / "nginx.conf").write_text(
        nginx_conf(tmp, nport, [(f"r{r}", p) for r, p in enumerate(ports)]))
    nginx = shutil.which("nginx") or "/usr/sbin/nginx"
    procs.append(subprocess.Popen([nginx, "-p", f"{tmp}/", "-e", f"{tmp}/nginx.log",
                                   "-c", str(tmp / "nginx.conf")]))
    wait_http(nport, "/healthz")
    return ports, nport


def upload_bunny(port):
    c = http.client.HTTPConnection("127.0.0.1", port)
    c.request("POST", "/v1/meshes", (ROOT / "tests" / "data" / "bunny00.off").read_bytes(),
              {"Content-Type": "model/off"})
    res = c.getresponse()
    body = res.read()
    if res.status not in (200, 201):
        raise RuntimeError(f"upload: {res.status} {body!r}")
    return json.loads(body)


def render(conn, path, request):
    conn.request("POST", path, json.dumps(request), {"Content-Type": "application/json"})
    res = conn.getresponse()
    data = res.read()
    if res.status != 200:
        raise RuntimeError(f"{path}: {res.status} {data[:200]!r}")
    return data


def split_render(args, build):
    """--split-render: one frame direct vs split over replicas through nginx (module docstring)."""
    server_bin = build / "server" / "kdrt-server"
    cli = build / "client" / "kdrt"
    width, height = (int(v) for v in args.size.split("x"))
    parts = args.split_render
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="kdrt-nginx-bench-"))
    procs = []
    try:
        ports, nport = start_stack(server_bin, tmp, args.replicas, procs)
        mesh = upload_bunny(nport)["id"]
        print(f"{args.replicas} kdrt-server replicas, nginx 127.0.0.1:{nport}, mesh {mesh} "
              f"(bunny00.off), {width}x{height} eyelight, {parts} bands")
        frame = {"mesh": mesh, "width": width, "height": height}
        direct = http.client.HTTPConnection("127.0.0.1", ports[0])
        nginx_url = f"http://127.0.0.1:{nport}"
        out = tmp / "split.png"
        command = [str(cli), "--server", nginx_url, "render", mesh, "-o", str(out), "--size",
                   args.size, "--split", str(parts), "--connections", str(parts), "--quiet"]
        band_conns = [http.client.HTTPConnection("127.0.0.1", nport) for _ in range(parts)]
        bands = [(height * k // parts, height * (k + 1) // parts) for k in range(parts)]

        def raw_split():
            answers = [None] * parts
            errors = []

            def one(k):
                y0, y1 = bands[k]
                try:
                    answers[k] = render(band_conns[k], f"/v1/render?route={mesh}.{k}", dict(
                        frame, format="raw", tile={"x": 0, "y": y0, "w": width, "h": y1 - y0}))
                except Exception as e:  # reported below
                    errors.append(e)

            threads = [threading.Thread(target=one, args=(k,)) for k in range(parts)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            if errors:
                raise errors[0]
            return answers

        def split_cli():
            run = subprocess.run(command, capture_output=True, text=True)
            if run.returncode != 0:
                raise RuntimeError(f"kdrt render --split: {run.returncode} {run.stderr}")

        def cli_start():
            subprocess.run([str(cli), "--help"], capture_output=True, check=True)

        cases = [
            ("direct PNG", lambda: render(direct, "/v1/render", frame)),
            ("split CLI PNG", split_cli),
            ("kdrt --help", cli_start),
            ("raw direct", lambda: render(direct, "/v1/render", dict(frame, format="raw"))),
            ("raw split", raw_split),
        ]
        png = render(direct, "/v1/render", frame)
        for _, run in cases:
            run()  # warm-up: every replica loads the tree, every connection is open
        if out.read_bytes() != png:
            raise RuntimeError("kdrt render --split wrote another PNG than the direct render")
        whole = render(direct, "/v1/render", dict(frame, format="raw"))
        band_pixels = b"".join(a[32:] for a in raw_split())
        if band_pixels != whole[32:]:
            raise RuntimeError("the raw bands do not put together the direct raw frame")
        times = {name: [] for name, _ in cases}
        for _ in range(args.reps):
            for name, run in cases:
                t0 = time.perf_counter()
                run()
                times[name].append(time.perf_counter() - t0)
        for name, _ in cases:
            s = times[name]
            print(f"{name:>14}: median {statistics.median(s) * 1e3:8.1f} ms  min "
                  f"{min(s) * 1e3:8.1f} ms  max {max(s) * 1e3:8.1f} ms  ({len(s)} renders)")
        print(f"split CLI PNG / direct PNG: "
              f"{statistics.median(times['split CLI PNG']) / statistics.median(times['direct PNG']):.2f}x; "
              f"raw split / raw direct: "
              f"{statistics.median(times['raw split']) / statistics.median(times['raw direct']):.2f}x "
              f"(same bytes checked)")
    finally:
        stop(procs)
        shutil.rmtree(tmp, ignore_errors=True)


def stop(procs):
    """SIGQUIT to nginx (the last process), SIGTERM to the servers; waits for them."""
    for p in reversed(procs):
        p.send_signal(signal.SIGQUIT if p is procs[-1] and len(procs) > 1 else signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=15)
        except subprocess.TimeoutExpired:
            p.kill()


def percentile(samples, p):
    s = sorted(samples)
    return s[min(len(s) - 1, int(p / 100 * len(s)))]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--build", default=str(ROOT / "build" / "release"))
    ap.add_argument("--requests", type=int, default=2000)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--split-render", type=int, default=0, metavar="N",
                    help="measure a frame direct vs in N bands over --replicas through nginx")
    ap.add_argument("--replicas", type=int, default=3, help="with --split-render")
    ap.add_argument("--size", default="1024x768", help="with --split-render: WIDTHxHEIGHT")
    args = ap.parse_args()
    if args.split_render:
        return split_render(args, pathlib.Path(args.build))
    server_bin = pathlib.Path(args.build) / "server" / "kdrt-server"
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="kdrt-nginx-bench-"))
    procs = []
    try:
        (port,), nport = start_stack(server_bin, tmp, 1, procs)
        up = f"127.0.0.1:{port}"
        summary = upload_bunny(nport)
        mesh = summary["id"]
        path = f"/v1/meshes/{mesh}/intersect"
        direct = http.client.HTTPConnection("127.0.0.1", port)
        proxied = http.client.HTTPConnection("127.0.0.1", nport)
        # kdrt-server closes idle keep-alive connections after keep_alive_timeout_s (2 s) and
        # after 1000 requests: http.client reconnects transparently, on both sides alike.
        print(f"kdrt-server {up}, nginx 127.0.0.1:{nport}, mesh {mesh} (bunny00.off, "
              f"{summary['triangles']} triangles)")
        for rays in (1, 1000):
            batch = rays_body(rays, rays)
            for conn in (direct, proxied):
                for _ in range(50):
                    post(conn, path, batch)  # warm-up
            times = {"direct": [], "nginx": []}
            for _ in range(args.requests):
                for name, conn in (("direct", direct), ("nginx", proxied)):
                    t0 = time.perf_counter()
                    post(conn, path, batch)
                    times[name].append(time.perf_counter() - t0)
            for name in ("direct", "nginx"):
                s = times[name]
                print(f"{rays:>7} rays  {name:>6}: p50 {percentile(s, 50) * 1e6:8.1f} us  "
                      f"p99 {percentile(s, 99) * 1e6:8.1f} us  ({len(s)} requests)")
            add50 = percentile(times["nginx"], 50) - percentile(times["direct"], 50)
            add99 = percentile(times["nginx"], 99) - percentile(times["direct"], 99)
            print(f"{rays:>7} rays  nginx adds p50 {add50 * 1e6:+.1f} us, p99 {add99 * 1e6:+.1f} us")
        big = rays_body(1 << 20, 7)
        for conn in (direct, proxied):
            # Making the batch takes seconds, past keep_alive_timeout_s: the server has closed the
            # idle connections, and http.client would write 32 MiB into a closed socket.
            conn.close()
            post(conn, path, big)
        times = {"direct": [], "nginx": []}
        for _ in range(args.reps):
            for name, conn in (("direct", direct), ("nginx", proxied)):
                t0 = time.perf_counter()
                post(conn, path, big)
                times[name].append(time.perf_counter() - t0)
        for name in ("direct", "nginx"):
            med = statistics.median(times[name])
            print(f"1M rays  {name:>6}: median {med * 1e3:8.1f} ms  {(1 << 20) / med / 1e6:6.2f} "
                  f"Mrays/s  ({args.reps} batches)")
    finally:
        stop(procs)
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
