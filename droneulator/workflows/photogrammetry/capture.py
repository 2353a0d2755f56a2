"""``droneulator capture``: fly circular rings of viewpoints around a tree and record a COLMAP dataset.

The client works like a user's own script against a running simulator, on its public interfaces
only: the tree's position comes from the API's ``scene_info`` landmarks, waypoints go out over the
WebSocket API, and everything recorded comes back from the ROS 2 topics over Zenoh. The stages:

1. :mod:`.plan`: the viewpoints and the arcs between them (pure geometry);
2. :mod:`.fly`: min-snap ``goto`` legs over the API, settled when the odometry says so;
3. :mod:`.record`: the next RGB frame after settling (the simulator's camera is triggered there, when
   its ``scene_info`` says ``camera_trigger: command``), the segmentation and depth of its stamp, its
   camera_info and the camera pose from TF;
4. :mod:`.dataset`: the dataset folder, written view by view (on a thread of its own, while the
   vehicles fly on); running the same command again captures only the views that are missing. The true
   tree and ground (:mod:`.truth`) go to ``truth/mesh.npz`` for ``droneulator score``.

Without ``--url`` the capture starts its own ``droneulator run`` (:func:`~droneulator.runtime.launch.
launch_run`) with the capture camera, triggered at the views unless ``capture.trigger`` is off (then it
shoots at ``capture.camera_hz``), logging to ``simulator.log`` in the dataset folder. When the
camera pitch is to be aimed at the crown, a short first run answers ``scene_info`` before the
capture camera's mount can be chosen.

``capture.vehicles`` (``--vehicles N``) flies N vehicles at once, each on its own contiguous arc of
every ring (:func:`~.plan.fleet_routes`; two: mirrored halves, from where they stand outwards), each with
its own WebSocket client, topics and thread; every image comes from the topics of the vehicle that flew to
its view. The views, their names and the dataset are those of one vehicle.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from droneulator.api.client import DroneulatorClient
from droneulator.config import CameraConfig, CaptureConfig, SimConfig, fleet
from droneulator.ros.topics import ns_to_seconds
from droneulator.ros.zenoh_node import RosZenohNode
from droneulator.runtime.launch import launch_run
from droneulator.scenes import get_scene
from droneulator.workflows.photogrammetry.dataset import CaptureDataset, plan_settings
from droneulator.workflows.photogrammetry.fly import Flyer, StoppedError
from droneulator.workflows.photogrammetry.plan import (
    Viewpoint,
    aim_pitch_deg,
    arc_waypoints,
    fleet_routes,
    mirrored_halves,
    pending_views,
    plan_viewpoints,
    ring_neighbours,
)
from droneulator.workflows.photogrammetry.record import (
    TfBuffer,
    TopicRecorder,
    camera_info_dict,
    record_view,
    vehicle_streams,
)
from droneulator.workflows.photogrammetry.truth import truth_mesh

#: the capture camera's mount, as the default camera's (body FLU, m)
MOUNT = CameraConfig().position
#: the true ground is kept this far beyond the orbit radius (what the cameras see of it near the tree)
TRUTH_GROUND_MARGIN_M = 5.0


#: the configured camera's settings the capture camera keeps: how the sensor renders light, none of
#: its geometry (the dataset's camera is a pinhole of ``capture``'s resolution and field of view)
PHOTOMETRIC_FIELDS = ("rgb_noise", "exposure_s", "auto_exposure")


def camera_for(cap: CaptureConfig, pitch_deg: float, like: CameraConfig | None = None) -> CameraConfig:
    """The capture camera: ``cap``'s resolution and field of view, at the default mount, pitched down,
    with the sensor noise and exposure of ``like`` (the config's camera of that name, when it has one),
    so that ``--set 'render.cameras=[{"rgb_noise": "machine_vision"}]'`` reaches the capture."""
    return CameraConfig(
        name=cap.camera,
        width=cap.width,
        height=cap.height,
        hfov_deg=cap.hfov_deg,
        rpy_deg=(0.0, pitch_deg, 0.0),
        **({f: getattr(like, f) for f in PHOTOMETRIC_FIELDS} if like is not None else {}),
    )


def tree_landmarks(info: dict[str, Any]) -> tuple[np.ndarray, float]:
    """The tree to orbit, from a ``scene_info`` reply: its trunk position (x, y, z) and the height to aim
    the camera at (the ``crown_center`` landmark's, else the trunk's)."""
    landmarks = info.get("landmarks", {})
    if "tree" not in landmarks:
        raise ValueError(
            f"scene {info.get('name')!r} has no 'tree' landmark to capture around "
            f"(landmarks: {', '.join(sorted(landmarks)) or 'none'}); try --scene tree_inspection"
        )
    center = np.asarray(landmarks["tree"], dtype=float).reshape(-1)
    if center.shape != (3,):
        raise ValueError(f"the 'tree' landmark must be [x, y, z], got {landmarks['tree']!r}")
    crown = np.asarray(landmarks.get("crown_center", center), dtype=float).reshape(-1)
    return center, float(crown[2])


def aim_pitch(cap: CaptureConfig, info: dict[str, Any]) -> float:
    """Mount pitch (deg) that points the capture camera at the crown from the mean ring altitude."""
    _, look_at_z = tree_landmarks(info)
    return aim_pitch_deg(cap.radius, cap.ring_altitudes(), look_at_z, MOUNT)


def run_config(cfg: SimConfig, pitch_deg: float) -> SimConfig:
    """The config of the simulator a capture starts: lockstep, the capture camera alone (keeping the
    sensor noise and exposure of the config's camera of its name), triggered at the views with the states
    at ``capture.state_hz`` (``capture.trigger``), no sensor topics; with ``capture.vehicles`` above one,
    that many vehicles (the config's own ``vehicles`` if it names them, else ``uav0`` ..), each with the
    capture camera."""
    cap = cfg.capture
    run_cfg = copy.deepcopy(cfg)
    run_cfg.runtime.mode = "lockstep"
    like = next((c for c in cfg.render.cameras if c.name == cap.camera), None)
    run_cfg.render.cameras = [camera_for(cap, pitch_deg, like)]
    run_cfg.render.camera_hz = cap.camera_hz
    run_cfg.render.camera_trigger = "command" if cap.trigger else "rate"
    if cap.trigger and cap.state_hz is not None:
        run_cfg.runtime.state_hz = cap.state_hz
    run_cfg.bridge.jpeg_quality = cap.jpeg_quality
    # no IMU, GPS or other sensor topics: the capture reads odometry, TF and images, and with a triggered
    # camera publishing the states is most of what the run does between views
    run_cfg.vehicle.sensors = []
    if cap.vehicles > 1:
        specs = run_cfg.vehicles if len(run_cfg.vehicles) >= cap.vehicles else fleet(cap.vehicles)
        run_cfg.vehicles = [dataclasses.replace(v, cameras=None, sensors=[]) for v in specs]
    return run_cfg


def write_truth(cfg: SimConfig, out: Path, info: dict[str, Any]) -> None:
    """The true tree and the ground around it (``truth/mesh.npz``), from the scene the simulator runs
    (rebuilt here from its name and seed, which ``scene_info`` confirmed): the scorer's reference."""
    from droneulator.scenes import get_scene

    scene = get_scene(info["name"], int(info["seed"]), float(info.get("vegetation", 1.0)))
    tree_radius = float(np.asarray(scene.landmarks.get("crown_radius", [3.0])).reshape(-1)[0]) + 1.0
    truth_mesh(scene, tree_radius, ground_radius=cfg.capture.radius + TRUTH_GROUND_MARGIN_M).save(
        Path(out) / "truth" / "mesh.npz"
    )


def scene_landmarks(cfg: SimConfig) -> dict[str, Any]:
    """The ``name`` and ``landmarks`` of ``cfg.scene`` as ``scene_info`` gives them, from the seeded scene
    built here (the capture camera's pitch depends on the tree's landmarks, and a run's camera rig is fixed
    when it starts: reading them here spares a probe run of the simulator)."""
    scene = get_scene(cfg.scene, cfg.seed, cfg.vegetation)
    return {"name": scene.name, "landmarks": {k: np.asarray(v).tolist() for k, v in scene.landmarks.items()}}


def capture(
    cfg: SimConfig,
    out: Path,
    url: str | None = None,
    zenoh_endpoint: str | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Capture ``cfg.capture.views`` views of ``cfg.scene`` into ``out`` (resuming what is there).

    Without ``url`` a ``droneulator run`` child process is started with the capture camera and stopped
    at the end; with ``url`` the simulator at that WebSocket URL is used (its camera rig as it is) and
    its ROS topics are read from ``zenoh_endpoint`` (default: ``cfg.bridge.listen``).
    """
    out = Path(out)
    draw = None
    if cfg.randomize.enabled:  # domain randomisation: one draw of conditions for the whole capture
        draw = cfg.randomize.draw(np.random.default_rng([cfg.seed, 0x52414E44]), cfg.wind)
        cfg = cfg.randomize.apply(cfg, draw)
        log(f"randomised conditions: {draw.describe()}")
    cap = cfg.capture
    wall0 = time.monotonic()
    timings: dict[str, float] = {}
    with contextlib.ExitStack() as stack:
        if url is None:
            sim_log = out / "simulator.log"
            pitch = cap.pitch_deg
            if pitch is None:
                pitch = aim_pitch(cap, scene_landmarks(cfg))
            run = stack.enter_context(launch_run(run_config(cfg, pitch), log=sim_log))
            api_url = run.url
            client = run.client()
            zenoh_endpoint = run.zenoh_endpoint
        else:
            api_url = url
            client = DroneulatorClient(url, timeout=30.0)
            zenoh_endpoint = zenoh_endpoint or cfg.bridge.listen[0]
        stack.callback(_close_quietly, client)
        info = client.scene_info()
        if (info["name"], info["seed"]) != (cfg.scene, cfg.seed):
            log(
                f"resetting the simulator from {info['name']} (seed {info['seed']}) "
                f"to {cfg.scene} (seed {cfg.seed})"
            )
            client.reset(scene=cfg.scene, seed=cfg.seed)
            info = client.scene_info()
        center, _ = tree_landmarks(info)
        # a client of the run's session, not a router of its own: as a router it joined the routers the
        # run links to (bridge.connect), and one with an ACL (docs/security.md) then cut it off the run's
        # topics (a sweep job behind --zenoh-router got no camera_info)
        node = stack.enter_context(
            RosZenohNode.from_config(cfg.bridge, mode="client", listen=(), connect=(zenoh_endpoint,))
        )
        pilots = _pilots(cfg, info, node, client, api_url, stack)
        topics = pilots[0].topics
        if info.get("camera_trigger") == "command":  # one frame set each for the camera's calibration
            for p in pilots:
                p.triggered = True
                p.client.trigger(vehicle=p.name)
        cam = camera_info_dict(topics.camera_info(timeout=60.0))
        for p in pilots[1:]:
            other = camera_info_dict(p.topics.camera_info(timeout=60.0))
            if other["K"] != cam["K"] or (other["width"], other["height"]) != (cam["width"], cam["height"]):
                raise ValueError(
                    f"{p.name}'s {cap.camera} camera differs from {pilots[0].name}'s: {other} != {cam}"
                )
        T_base_opt = topics.tf.lookup(
            topics.base_frame, cam["frame_id"], topics.latest_odom().stamp, timeout=30.0
        )
        pitch_used = math.degrees(math.asin(float(np.clip(T_base_opt[:3, 2] @ [0.0, 0.0, -1.0], -1, 1))))
        # the dataset's camera is the same on every vehicle: its frame without the vehicle's TF prefix
        # (each view keeps the frame id its image came with)
        cam["frame_id"] = cam["frame_id"].removeprefix(topics.frame_prefix)
        if url is not None:
            pitch = pitch_used
        settings = plan_settings(cfg, pitch, cam)
        if draw is not None:  # part of the plan: a resumed capture must fly in the same conditions
            settings["conditions"] = dataclasses.asdict(draw)
        dataset = CaptureDataset.open(out, settings)
        dataset.set_camera(cam)
        write_truth(cfg, out, info)
        timings["startup_s"] = time.monotonic() - wall0
        plan = plan_viewpoints(center, cap.radius, cap.ring_altitudes(), cap.views, cap.arc_deg)
        log(
            f"capture {cfg.scene} (seed {cfg.seed}): {len(plan)} views on "
            f"{len(cap.ring_altitudes())} ring(s), "
            f"radius {cap.radius} m, altitudes {cap.ring_altitudes()} m, pitch {pitch:.1f} deg, "
            f"{cam['width']}x{cam['height']}, {len(plan) - len(pending_views(plan, dataset.views))} "
            f"already in {out}" + (f"; {len(pilots)} vehicles" if len(pilots) > 1 else "")
        )
        routes = fleet_routes(plan, center, [p.topics.latest_odom().position for p in pilots], cap.arc_deg)
        for p, route in zip(pilots, routes, strict=True):
            p.route = pending_views(route, dataset.views)
        run_record = _fly_and_record(pilots, dataset, cam, plan, cap, center, timings, wall0, progress)
        meta = dataset.metadata(None)
        tr = meta["tracking"]
        log(
            f"captured {run_record['captured']} view(s) in {run_record['wall_s']:.1f} s wall "
            f"({run_record.get('sim_s', 0.0):.1f} s sim, the legs "
            f"{run_record.get('legs_sim_s', 0.0):.1f} s); "
            f"{len(dataset.views)}/{len(plan)} in {out}; "
            f"max tracking error over {tr['capture_legs']} capture legs: "
            f"path {_fmt_m(tr['max_path_error_m'])}, altitude {_fmt_m(tr['max_altitude_error_m'])}"
        )
        return meta


@dataclass
class _Pilot:
    """One vehicle of the capture: its name, client, topics and the views it is to fly, in order."""

    name: str
    client: DroneulatorClient
    topics: TopicRecorder
    #: the simulator's takeoff altitude (``scene_info.limits``): a vehicle on the ground climbs to this (or to
    #: its first view, if lower) and flies up and across to its first view at once
    takeoff_altitude: float
    route: list[Viewpoint] = dataclasses.field(default_factory=list)
    #: the simulator's cameras shoot only when triggered (``scene_info.camera_trigger``): one at each view
    triggered: bool = False


def _pilots(
    cfg: SimConfig,
    info: dict[str, Any],
    node: RosZenohNode,
    client: DroneulatorClient,
    url: str,
    stack: contextlib.ExitStack,
) -> list[_Pilot]:
    """The first ``capture.vehicles`` vehicles of ``scene_info``, each with a client (the first has
    ``client``, the others their own connections to ``url``) subscribed to events, and its topics."""
    n = cfg.capture.vehicles
    vehicles = info.get("vehicles") or [{"name": "uav0"}]
    if len(vehicles) < n:
        raise ValueError(
            f"capture.vehicles is {n} but the simulator has {len(vehicles)} vehicle(s): "
            f"{', '.join(v['name'] for v in vehicles)}"
        )
    b = cfg.bridge
    buffers: dict[str, TfBuffer] = {}
    pilots = []
    for k, v in enumerate(vehicles[:n]):
        names, prefix = vehicle_streams(v, cfg.capture.camera, b.namespace, len(vehicles) > 1, b.fleet_tf)
        shared = buffers.get(names["tf"])
        topics = TopicRecorder(node, names, prefix, shared)
        buffers.setdefault(names["tf"], topics.tf)
        if k == 0:
            c = client
        else:
            c = DroneulatorClient(url, timeout=30.0)
            stack.callback(_close_quietly, c)
        c.subscribe(["events"])
        pilots.append(_Pilot(v["name"], c, topics, float(info["limits"]["takeoff_altitude"])))
    return pilots


def _fly_and_record(
    pilots: list[_Pilot],
    dataset: CaptureDataset,
    cam: dict[str, Any],
    plan: list[Viewpoint],
    cap: CaptureConfig,
    center: Sequence[float],
    timings: dict[str, float],
    wall0: float,
    progress: bool,
) -> dict[str, Any]:
    """Take off if needed and fly every pilot's route (several at once in a thread each), storing each
    view as it comes; the run's record for the metadata (written even when the flight stops early, so
    the dataset stays consistent)."""
    clock = pilots[0].topics
    t_sim0 = clock.latest_odom().stamp
    run: dict[str, Any] = {"started": time.strftime("%Y-%m-%d %H:%M:%S"), "captured": 0}
    if len(pilots) > 1:
        run["vehicles"] = {p.name: len(p.route) for p in pilots}
    todo = sum(len(p.route) for p in pilots)
    lock = threading.Lock()
    legs = dict.fromkeys((p.name for p in pilots), 0.0)
    bar = tqdm(total=len(plan), initial=len(plan) - todo, unit="view", desc="capture", disable=not progress)
    writer = _Writer(dataset, bar)

    def store(p: _Pilot, record: dict[str, Any], jpeg: bytes, aux: Any, settled: int, err: str) -> None:
        with lock:
            run["captured"] += 1
            run["wall_s"] = time.monotonic() - wall0
            run["sim_s"] = max(run.get("sim_s", 0.0), ns_to_seconds(settled - t_sim0))
            legs[p.name] += record["leg"]["flight_sim_s"] + record["leg"]["settle_sim_s"]
            run["legs_sim_s"] = round(max(legs.values()), 3)
            writer.put(record, jpeg, aux, dict(run), err if len(pilots) == 1 else f"{p.name} {err}")

    t_fly = time.monotonic()
    try:
        _fly_all(pilots, plan, cam, cap, center, timings, store)
    finally:
        failed = writer.close()
        bar.close()
        run["captured"] = writer.stored
        timings["flight_s"] = time.monotonic() - t_fly
        run["wall_s"] = time.monotonic() - wall0
        with contextlib.suppress(TimeoutError):
            run["sim_s"] = ns_to_seconds(clock.latest_odom(timeout=1.0).stamp - t_sim0)
        run["timings"] = {k: round(v, 3) for k, v in timings.items()}
        run["complete"] = len(dataset.views) == len(plan)
        if dataset.camera is not None:
            dataset.finish_run(run)
        if failed is not None:
            raise RuntimeError(f"storing the views failed: {failed}") from failed
    return run


class _Writer:
    """Stores the views on a thread of its own, in the order they come, so that the vehicles fly on while
    a view's files are compressed and written; the files that list the views are written once for every
    batch of views that waited meanwhile. A failed write stops the capture at its next view."""

    def __init__(self, dataset: CaptureDataset, bar: tqdm) -> None:
        self.dataset, self.bar = dataset, bar
        self.queue: queue.Queue[tuple[dict[str, Any], bytes, Any, dict[str, Any], str] | None] = queue.Queue()
        self.error: BaseException | None = None
        #: views stored (their files and their entries in the lists)
        self.stored = 0
        self.thread = threading.Thread(target=self._main, name="capture-writer", daemon=True)
        self.thread.start()

    def put(self, record: dict[str, Any], jpeg: bytes, aux: Any, run: dict[str, Any], postfix: str) -> None:
        """Queue one view (``run``: the run's record as of this view, for the metadata)."""
        if self.error is not None:
            raise RuntimeError(f"storing the views failed: {self.error}") from self.error
        self.queue.put((record, jpeg, aux, run, postfix))

    def _main(self) -> None:
        done = False
        while not done:
            batch = [self.queue.get()]
            while not self.queue.empty():
                batch.append(self.queue.get_nowait())
            done = batch[-1] is None
            views = [b for b in batch if b is not None]
            if not views or self.error is not None:
                continue
            try:
                for record, jpeg, aux, _, _ in views:
                    self.dataset.store(record, jpeg, aux)
                self.dataset.write(views[-1][3])
            except Exception as e:  # raised to the flight by put(), returned by close()
                self.error = e
                continue
            self.stored += len(views)
            self.bar.set_postfix_str(views[-1][4])
            self.bar.update(len(views))

    def close(self) -> BaseException | None:
        """Store what is queued, then stop; the write error that stopped the storing, if one did."""
        self.queue.put(None)
        self.thread.join()
        return self.error


def _fly_all(
    pilots: list[_Pilot],
    plan: list[Viewpoint],
    cam: dict[str, Any],
    cap: CaptureConfig,
    center: Sequence[float],
    timings: dict[str, float],
    store: Callable[..., None],
) -> None:
    """Fly the pilots' routes: one in this thread; several in a thread each, which wait for each other
    at their first views (so that they fly their arcs in step) and all stop when one fails."""
    active = [p for p in pilots if p.route]
    fleet = len(pilots) > 1
    # vehicles flying arcs the same way round start a quarter turn or more from where they stand, and first
    # move apart along the circle; mirrored halves start next to them
    arc_first = fleet and not mirrored_halves(len(pilots), cap.arc_deg)
    if len(active) <= 1:
        for p in active:
            _fly_route(p, plan, cam, cap, center, timings, store, None, None, fleet, arc_first)
        return
    stop = threading.Event()
    barrier = threading.Barrier(len(active))
    errors: list[BaseException] = []

    def main(p: _Pilot) -> None:
        try:
            _fly_route(p, plan, cam, cap, center, timings, store, stop, barrier, fleet, arc_first)
        except BaseException as e:  # every failure stops the other vehicles, and is raised below
            errors.append(e)
            stop.set()
            barrier.abort()

    threads = [threading.Thread(target=main, args=(p,), name=f"capture-{p.name}") for p in active]
    for t in threads:
        t.start()
    try:
        for t in threads:
            while t.is_alive():
                t.join(0.2)
    except BaseException:
        stop.set()
        barrier.abort()
        for t in threads:
            t.join()
        raise
    causes = [e for e in errors if not isinstance(e, StoppedError | threading.BrokenBarrierError)]
    if errors:
        raise (causes or errors)[0]


def _fly_route(
    p: _Pilot,
    plan: list[Viewpoint],
    cam: dict[str, Any],
    cap: CaptureConfig,
    center: Sequence[float],
    timings: dict[str, float],
    store: Callable[..., None],
    stop: threading.Event | None,
    barrier: threading.Barrier | None,
    fleet: bool,
    arc_first: bool,
) -> None:
    """Take ``p``'s vehicle off if it is on the ground (to the simulator's takeoff altitude, or its first
    view's if lower: the first transit climbs the rest of the way) and fly it to each view of its route,
    recording each; consecutive views next to each other on a ring are joined by a capture leg along the
    arc, other views by a transit (``arc_first``: :meth:`.fly.Flyer.transit`'s)."""
    client, topics, vehicle = p.client, p.topics, p.name
    flyer = Flyer(client, topics, cap, center, vehicle=vehicle, stop=stop)
    state = client.state(vehicle=vehicle)
    if state["mode"] in ("idle", "collided") or state["position"][2] < 0.3:
        t = time.monotonic()
        client.takeoff(altitude=min(p.takeoff_altitude, float(p.route[0].position[2])), vehicle=vehicle)
        client.wait_for_event("arrived", timeout=cap.leg_timeout_s, vehicle=vehicle)
        timings[f"takeoff_s_{vehicle}" if fleet else "takeoff_s"] = time.monotonic() - t
    previous: Viewpoint | None = None
    for view in p.route:
        adjacent = (
            previous is not None
            and ring_neighbours(plan, previous, view)
            and flyer.commanded is not None
            and np.allclose(flyer.commanded, previous.position)
        )
        if adjacent:
            assert previous is not None
            pts = arc_waypoints(
                center, cap.radius, view.position[2], previous.azimuth, view.azimuth, cap.max_leg_deg
            )
            stats, settled = flyer.fly(pts, "capture")
        else:
            stats, settled = flyer.transit(view, cap.radius, arc_first=arc_first)
        if settled is None:
            raise RuntimeError(f"no leg was flown to reach view {view.name}")
        if p.triggered:
            client.trigger(vehicle=vehicle)
        record, jpeg, aux = record_view(topics, view, cam, settled, stats.to_dict(), vehicle)
        err = f"path_err={stats.max_path_error_m:.3f}m, alt_err={stats.max_altitude_error_m:.3f}m"
        store(p, record, jpeg, aux, settled, err)
        if previous is None and barrier is not None:
            barrier.wait(timeout=cap.leg_timeout_s * 10)
        previous = view


def _close_quietly(client: DroneulatorClient) -> None:
    with contextlib.suppress(Exception):  # the simulator may be gone already; closing must still succeed
        client.close()


def _fmt_m(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f} m"
