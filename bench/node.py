"""Benchmark the real outcome_node over DDS: end-to-end latency, 30 Hz throughput, memory.

    python bench/node.py                  # 5 scenarios, 60 s of 30 Hz each (~7-8 min)
    python bench/node.py --seconds 120
    python bench/node.py --quick          # a smoke run (~1.5 min)
    python bench/node.py --only shm_sensor_data_static   # one scenario, printed only

Per scenario the node runs as its own process (the ``outcome_node`` console script, default
parameters except model_path and qos) and a client process (bench/_node_client.py) publishes
640 x 480 32FC1 frames on depth/image_raw and subscribes outcome/labels and outcome/status.
Scenarios: input QoS best effort (node qos:=sensor_data, publisher best effort depth 5) or
reliable (qos:=reliable, publisher reliable depth 5), each with and without the Fast DDS SHM
profile (config/fastdds_shm.xml via FASTRTPS_DEFAULT_PROFILES_FILE, for both processes);
"no SHM profile" means Fast DDS's built-in transports (``host_udp_datagrams_during`` hints
how much went over UDP, but the counters are host-wide: other processes add to them). Frames
come from many cameras (every dataset image has its own, so the support plane is refitted
each frame), and in one more best-effort SHM scenario from one static camera (one image with
fresh noise each frame: the node keeps its plane, ``reuse_floor_fit``).

* latency (best-effort scenarios): one frame at a time at 10 Hz, publish -> labels received,
  interleaved frame by frame with the **floor**: a do-nothing node (bench/_floor_node.py)
  beside the real one, fed by the same publisher with the same profile, that answers each
  frame at once with the same messages. ``ratio_to_floor`` = outcome_node / floor; CPU time
  per frame for both;
* throughput: 30 Hz for ``--seconds``: fraction answered, node dropped_frames (newest-frame
  policy), frames lost before the node, answer lag and backlog, node CPU and RSS over time.

``--tiny-network`` runs the latency phase of the best-effort SHM scenarios with the shipped
checkpoint's network swapped for a one-level one of the same inputs and classes
(``inference.tiny_network_model``): what the node costs but for its network, against the same
floor. It writes the ``node_tiny_network`` section instead of ``node``.

``--reference REV`` puts outcome_node as it was at git revision REV, with the model it shipped,
in the floor's place (checked out into a temporary worktree, run with this environment's
packages), so a change to the node is measured against its past in the same run, frame by
frame: latency and CPU time per frame as ratios to the reference. It writes the
``node_reference`` section instead of ``node``.

Every scenario gets its own random ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST.
Writes the ``node`` section of bench/results.json.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import record, sha256  # noqa: E402
from inference import load_average, prepare_model, tiny_network_model  # noqa: E402

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
SHM_PROFILE = REPO / "config" / "fastdds_shm.xml"
PROFILE_VARS = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
# name -> (input qos, Fast DDS SHM profile, static camera). Moving-camera frames refit the
# support plane each time; the static one is what a cell's fixed camera gives the node.
SCENARIOS = {
    "shm_sensor_data_static": ("sensor_data", True, True),
    "shm_sensor_data": ("sensor_data", True, False),
    "noshm_sensor_data": ("sensor_data", False, False),
    "shm_reliable": ("reliable", True, False),
    "noshm_reliable": ("reliable", False, False),
}


def node_command() -> list[str]:
    script = Path(sys.prefix) / "bin" / "outcome_node"
    if script.is_file():
        return [str(script)]
    found = shutil.which("outcome_node")
    return [found] if found else [sys.executable, "-m", "task_outcome_ros.node"]


def scenario_env(domain_id: int, shm: bool) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in PROFILE_VARS}
    env.update(ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1", RCUTILS_COLORIZED_OUTPUT="0")
    env.pop("ROS_LOCALHOST_ONLY", None)
    if shm:
        env.update(dict.fromkeys(PROFILE_VARS, str(SHM_PROFILE)))
    return env


def udp_counters() -> dict[str, int]:
    """Host-wide UDP counters (/proc/net/snmp): shows whether images went over UDP at all."""
    rows = [line.split() for line in Path("/proc/net/snmp").read_text().splitlines()
            if line.startswith("Udp:")]
    return {k: int(v) for k, v in zip(rows[0][1:], rows[1][1:], strict=True)
            if k in ("InDatagrams", "OutDatagrams", "RcvbufErrors", "InErrors")}


def stop(proc: subprocess.Popen | None, timeout: float = 10.0) -> None:
    """SIGINT, then SIGKILL if it does not exit; only this process, by its id."""
    if proc is None or proc.poll() is not None:
        return
    try:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout)


def floor_command(qos: str) -> list[str]:
    """The do-nothing node (bench/_floor_node.py) in the namespace the client feeds."""
    return [sys.executable, str(BENCH / "_floor_node.py"), "--qos", qos, "--ros-args",
            "-r", "__ns:=/floor"]


def reference_worktree(revision: str, tmp: Path) -> Path:
    """outcome_node's code and shipped model at ``revision``, checked out under ``tmp``."""
    where = tmp / "reference"
    subprocess.run(["git", "worktree", "add", "--detach", str(where), revision], cwd=REPO,
                   check=True, capture_output=True, text=True)
    return where


def reference_command(worktree: Path, qos: str) -> list[str]:
    """The node of ``worktree`` with its own shipped model, in the floor's namespace."""
    model = worktree / "task_outcome_ros" / "models" / "outcome_fcn.pt"
    return [sys.executable, "-m", "task_outcome_ros.node", "--ros-args", "-r", "__ns:=/floor",
            "-p", f"model_path:={model}", "-p", f"qos:={qos}"]


def run_scenario(model: Path, qos: str, shm: bool, latency_frames: int, seconds: float,
                 images: int, tmp: Path, timeout: float, static: bool = False,
                 reference: Path | None = None) -> dict:
    name = f"{'shm' if shm else 'noshm'}_{qos}{'_static' if static else ''}"
    domain_id = random.randint(1, 200)
    env = scenario_env(domain_id, shm)
    log_path, out = tmp / f"{name}.node.log", tmp / f"{name}.json"
    floor_log = tmp / f"{name}.floor.log"
    node = client = floor = None
    start, udp0, load0 = time.monotonic(), udp_counters(), load_average()
    try:
        with open(log_path, "w") as log, open(floor_log, "w") as flog:
            node = subprocess.Popen(
                node_command() + ["--ros-args", "-p", f"model_path:={model}", "-p", f"qos:={qos}"],
                env=env, stdout=log, stderr=subprocess.STDOUT)
            client_args = ["--node-pid", str(node.pid)]
            if latency_frames:  # the floor, measured in the same run, frame by frame
                if reference is None:
                    floor = subprocess.Popen(floor_command(qos), env=env, stdout=flog,
                                             stderr=subprocess.STDOUT)
                else:  # its imports must come from the worktree, not this checkout
                    floor = subprocess.Popen(
                        reference_command(reference, qos), stdout=flog,
                        stderr=subprocess.STDOUT, cwd=reference,
                        env={**env, "PYTHONPATH": os.pathsep.join(
                            p for p in (str(reference), env.get("PYTHONPATH")) if p)})
                client_args += ["--floor-pid", str(floor.pid)]
            client = subprocess.Popen(
                [sys.executable, str(BENCH / "_node_client.py"), *client_args,
                 "--qos", qos, "--latency-frames", str(latency_frames), "--seconds",
                 str(seconds), "--images", str(images), "--out", str(out)]
                + (["--static-camera"] if static else []), env=env)
            try:
                client.wait(timeout)
            except subprocess.TimeoutExpired:
                stop(client)
                raise
            node_alive = node.poll() is None
    finally:
        stop(client)
        stop(floor)
        stop(node)
    udp1 = udp_counters()
    log_text = log_path.read_text()
    result = json.loads(out.read_text()) if out.exists() else {"ok": False,
                                                                "error": "no client output"}
    result.update(scenario=name, shm_profile=shm, node_qos=qos, static_camera=static,
                  domain_id=domain_id,
                  wall_s=round(time.monotonic() - start, 1), node_alive_at_end=node_alive,
                  node_exit_code=node.returncode, load_average_before=load0,
                  load_average_after=load_average(),
                  host_udp_datagrams_during={k: udp1[k] - udp0[k] for k in udp0})
    line = ready_line(log_text)  # a model in the temp folder: its file name says enough
    result["node_ready_line"] = line and line.replace(f"{tmp}/", "")
    if reference is not None:  # worktree paths say which revision, not where it was
        line = ready_line(floor_log.read_text())
        result["reference_ready_line"] = line and line.replace(f"{reference}/", "")
    if not result.get("ok"):
        result["node_log_tail"] = log_text[-2000:]
    return result


def ready_line(log_text: str) -> str | None:
    """What outcome_node said it loaded ("... ready: <this>"), from its log."""
    ready = [line for line in log_text.splitlines() if "ready:" in line]
    return ready[0].split("ready:", 1)[1].strip() if ready else None


def summary(s: dict) -> dict:
    """The few figures worth reading first, per scenario."""
    out = {"ok": s.get("ok")}
    lat = s.get("latency")
    if lat:
        e2e = lat.get("end_to_end_ms") or {}
        floor_lat = lat.get("floor") or {}
        floor = floor_lat.get("end_to_end_ms") or {}
        out.update(latency_p50_ms=e2e.get("p50"), latency_p95_ms=e2e.get("p95"),
                   latency_unanswered=f"{lat['unanswered']}/{lat['frames']}",
                   floor_p50_ms=floor.get("p50"), floor_p95_ms=floor.get("p95"),
                   ratio_to_floor=lat.get("ratio_to_floor"),
                   cpu_ms_per_frame=lat.get("cpu_ms_per_frame"),
                   floor_cpu_ms_per_frame=floor_lat.get("cpu_ms_per_frame"))
    tp = s.get("throughput")
    if tp:
        out.update(fraction_answered=tp["fraction_answered"], answered_hz=tp["answered_hz"],
                   dropped_frames_node=tp["dropped_frames_node"],
                   lost_before_node=tp["lost_before_node"],
                   lag_p50_ms=tp["lag_ms"]["p50"] if tp["lag_ms"] else None,
                   max_backlog_frames=tp["backlog_frames"]["max"],
                   node_rss_mb_start_end=[round(tp["node_rss_kb"]["start"] / 1024, 1),
                                          round(tp["node_rss_kb"]["end"] / 1024, 1)],
                   node_cpu_percent=tp["node_cpu_percent"],
                   node_cpu_ms_per_answered_frame=tp.get("node_cpu_ms_per_answered_frame"),
                   support_plane_kept_share=tp.get("support_plane_kept_share"))
    return out


def exit_if_any_failed(scenarios: dict[str, dict]) -> None:
    """Print what went wrong in every scenario that is not ok (its error, if any, and the
    node's log tail) and exit without touching results.json."""
    failed = [name for name, s in scenarios.items() if not s.get("ok")]
    if not failed:
        return
    for name in failed:
        error = scenarios[name].get("error")
        print(f"[bench/node] {name} failed{f': {error}' if error else ''}\n"
              f"{scenarios[name].get('node_log_tail') or ''}", file=sys.stderr)
    sys.exit(f"bench/node.py: {', '.join(failed)} failed; results.json left unchanged")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=60.0,
                        help="30 Hz throughput phase per scenario (default 60)")
    parser.add_argument("--latency-frames", type=int, default=200,
                        help="one-at-a-time frames in the best-effort scenarios (default 200)")
    parser.add_argument("--images", type=int, default=30, help="distinct frames to cycle")
    parser.add_argument("--quick", action="store_true", help="10 s throughput, 50 latency frames")
    parser.add_argument("--only", choices=SCENARIOS, nargs="+", default=list(SCENARIOS),
                        help="run these scenarios only (results.json is left unchanged)")
    instead = parser.add_mutually_exclusive_group()
    instead.add_argument("--reference", metavar="REV",
                         help="measure against outcome_node at this git revision (its own "
                              "shipped model) instead of the do-nothing floor, in the "
                              "best-effort scenarios' latency phase only")
    instead.add_argument("--tiny-network", action="store_true",
                         help="measure the node with a network of almost no cost in the "
                              "best-effort SHM scenarios' latency phase (node_tiny_network)")
    args = parser.parse_args()
    if args.quick:
        args.seconds, args.latency_frames, args.images = 10.0, 50, 10
    command = "python bench/node.py " + " ".join(sys.argv[1:])

    def on_term(signum, frame):  # turn SIGTERM into the finally-blocks' cleanup
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    if args.reference:
        reference_main(args)
        return
    if args.tiny_network:
        tiny_network_main(args)
        return
    load_start = load_average()
    scenarios = []
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="bench_node_") as tmp:
        model, model_desc = prepare_model(Path(tmp))
        for name in args.only:
            qos, shm, static = SCENARIOS[name]
            lat = args.latency_frames if qos == "sensor_data" else 0
            timeout = 240 + args.seconds * 2 + lat * 0.5
            print(f"[bench/node] scenario shm={shm} qos={qos} static={static} ...", flush=True)
            s = run_scenario(model, qos, shm, lat, args.seconds, args.images, Path(tmp),
                             timeout, static)
            print(f"[bench/node]   {json.dumps(summary(s))}", flush=True)
            scenarios.append(s)
    if set(args.only) != set(SCENARIOS):  # a diagnosis run: printed, not recorded
        return
    exit_if_any_failed({s["scenario"]: s for s in scenarios})
    record("node", {
        "model": model_desc, "node_command": " ".join(node_command()),
        "node_params": "defaults (backend auto, publish_overlay true, publish_markers true, "
                       "reuse_floor_fit true) + model_path, qos; the client subscribes to "
                       "labels and status only, so overlay and markers are not computed",
        "floor_node": " ".join(floor_command("<qos>")),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
        "quick": args.quick, "wall_s": round(time.monotonic() - t0, 1),
        "load_average_1_5_15": {"start": load_start, "end": load_average()},
        "summary": {s["scenario"]: summary(s) for s in scenarios},
        "scenarios": {s["scenario"]: s for s in scenarios},
    }, command)


def reference_main(args: argparse.Namespace) -> None:
    """The latency phase of the best-effort scenarios against outcome_node at a past revision."""
    found = subprocess.run(["git", "rev-parse", "--verify", "--short=12",
                            f"{args.reference}^{{commit}}"], cwd=REPO, capture_output=True,
                           text=True)
    if found.returncode:
        sys.exit(f"bench/node.py: --reference {args.reference}: not a commit of this "
                 f"repository ({found.stderr.strip()})")
    revision = found.stdout.strip()
    command = "python bench/node.py " + " ".join(sys.argv[1:])
    every = [n for n in SCENARIOS if SCENARIOS[n][0] == "sensor_data"]
    names = [n for n in args.only if n in every]
    if not names:
        sys.exit(f"bench/node.py: --reference measures the best-effort scenarios' latency; "
                 f"--only chose none of {every}")
    load_start, t0, scenarios = load_average(), time.monotonic(), {}
    with tempfile.TemporaryDirectory(prefix="bench_node_") as tmp:
        model, model_desc = prepare_model(Path(tmp))
        worktree = reference_worktree(revision, Path(tmp))
        reference_sha = sha256(worktree / "task_outcome_ros" / "models" / "outcome_fcn.pt")
        try:
            for name in names:
                qos, shm, static = SCENARIOS[name]
                print(f"[bench/node] {name} against {revision} ...", flush=True)
                s = run_scenario(model, qos, shm, args.latency_frames, 0.0, args.images,
                                 Path(tmp), 240 + args.latency_frames, static, worktree)
                scenarios[name] = against_reference(s)
                print(f"[bench/node]   {json.dumps(scenarios[name]['summary'])}", flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(worktree)], cwd=REPO,
                           capture_output=True)
    exit_if_any_failed(scenarios)
    if set(names) != set(every):  # a diagnosis run: printed, not recorded
        return
    record("node_reference", {
        "model": model_desc, "reference_revision": revision,
        "reference_model_sha256": reference_sha,
        "reference": "outcome_node of the reference revision with the model it shipped, "
                     "default parameters + model_path, qos; the client subscribes to labels "
                     "and status only",
        "wall_s": round(time.monotonic() - t0, 1),
        "load_average_1_5_15": {"start": load_start, "end": load_average()},
        "scenarios": scenarios}, command)


def tiny_network_main(args: argparse.Namespace) -> None:
    """The latency phase of the best-effort SHM scenarios, the node running a network of
    almost no cost: how close to the floor the node's other work alone lets it come."""
    eligible = [n for n in SCENARIOS if SCENARIOS[n][0] == "sensor_data" and SCENARIOS[n][1]]
    names = [n for n in args.only if n in eligible]
    if not names:
        sys.exit(f"bench/node.py: --tiny-network measures the best-effort SHM scenarios' "
                 f"latency; --only chose none of {eligible}")
    command = "python bench/node.py " + " ".join(sys.argv[1:])
    load_start, t0, scenarios = load_average(), time.monotonic(), {}
    with tempfile.TemporaryDirectory(prefix="bench_node_") as tmp:
        shipped, shipped_desc = prepare_model(Path(tmp))
        model, model_desc = tiny_network_model(shipped, Path(tmp))
        for name in names:
            qos, shm, static = SCENARIOS[name]
            print(f"[bench/node] {name} with the tiny network ...", flush=True)
            s = run_scenario(model, qos, shm, args.latency_frames, 0.0, args.images,
                             Path(tmp), 240 + args.latency_frames, static)
            scenarios[name] = s
            print(f"[bench/node]   {json.dumps(summary(s))}", flush=True)
    exit_if_any_failed(scenarios)
    if set(names) != set(eligible):  # a diagnosis run: printed, not recorded
        return
    record("node_tiny_network", {
        "model": model_desc, "network_taken_from": shipped_desc,
        "node_command": " ".join(node_command()),
        "floor_node": " ".join(floor_command("<qos>")),
        "quick": args.quick, "wall_s": round(time.monotonic() - t0, 1),
        "load_average_1_5_15": {"start": load_start, "end": load_average()},
        "summary": {name: summary(s) for name, s in scenarios.items()},
        "scenarios": scenarios}, command)


def against_reference(s: dict) -> dict:
    """A scenario's latency phase with the floor's figures renamed for what they measured."""
    lat = dict(s.get("latency") or {})
    ref = lat.pop("floor", None) or {}
    lat.pop("ratio_to_floor", None)
    now, then = lat.get("end_to_end_ms") or {}, ref.get("end_to_end_ms") or {}
    ratios = {f"latency_{q}": round(now[q] / then[q], 2) for q in ("p50", "p95")
              if now.get(q) and then.get(q)}
    if lat.get("cpu_ms_per_frame") and ref.get("cpu_ms_per_frame"):
        ratios["cpu_per_frame"] = round(lat["cpu_ms_per_frame"] / ref["cpu_ms_per_frame"], 2)
    summary_row = {"latency_p50_ms": now.get("p50"), "reference_p50_ms": then.get("p50"),
                   "cpu_ms_per_frame": lat.get("cpu_ms_per_frame"),
                   "reference_cpu_ms_per_frame": ref.get("cpu_ms_per_frame"),
                   "unanswered": lat.get("unanswered"),
                   "reference_unanswered": ref.get("unanswered"), "ratios": ratios}
    return {"ok": bool(s.get("ok") and ratios.get("latency_p50")), "summary": summary_row,
            "latency": lat, "reference_latency": ref,
            "node_ready_line": s.get("node_ready_line"),
            "reference_ready_line": s.get("reference_ready_line"),
            "load_average_before": s.get("load_average_before"),
            "load_average_after": s.get("load_average_after"),
            "node_log_tail": s.get("node_log_tail")}


if __name__ == "__main__":
    main()
