#!/usr/bin/env python3
"""Record OptiTac through the LeRobot plugins beside a simulated 30-fps camera, as ``lerobot-record`` does, and
count what each source delivered and what the dataset holds (the check of docs/lerobot.md).

    python tools/lerobot_record_check.py --seconds 30 --workdir /tmp/rec-check

The plugins are found as LeRobot finds them (``register_third_party_plugins``: the installed distributions
``lerobot_robot_optitac`` and ``lerobot_camera_optitac``); the robot is made from its config by LeRobot
(``make_robot_from_config``) and the dataset's features from the robot's (``hw_to_dataset_features``); each tick
is ``lerobot-record``'s: ``get_observation()``, ``build_dataset_frame``, ``add_frame``, then a sleep to the next
tick. (``lerobot-record`` itself wants a teleoperator or a policy to act; the sensor alone has no actions.)

The simulated scene camera delivers a frame every 1/fps s in a thread of its own, stamped with its number; the
OptiTac sensor runs the built-in simulated board at ``--sensor-fps``. Printed: the dataset's frames; the scene
frames delivered, recorded and missed (delivered but never recorded, from the stamps); the sensor's frames
read and dropped by its camera while recording, and how many of them the dataset holds (the newest at each
tick) and how many are counted unread; the threads left after disconnect. Exit status 1 when a frame of either
source was lost uncounted or a thread is left.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
import types
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np


def _scene_camera_classes() -> tuple[type, type]:
    """A simulated scene camera with LeRobot's camera contract (registered as ``optitac_scene_sim``)."""
    from lerobot.cameras.camera import Camera
    from lerobot.cameras.configs import CameraConfig

    @CameraConfig.register_subclass("optitac_scene_sim")
    @dataclass(kw_only=True)
    class SceneSimConfig(CameraConfig):
        fps: int | None = 30
        width: int | None = 320
        height: int | None = 240

    class SceneSim(Camera):
        """A frame every 1/fps s; pixel (0, 0..3) holds its number (little-endian)."""

        def __init__(self, config: SceneSimConfig) -> None:
            super().__init__(config)
            self.config = config
            self.delivered = 0
            self._cond = threading.Condition()
            self._frame: np.ndarray | None = None
            self._fresh = False
            self._stop = threading.Event()
            self._thread: threading.Thread | None = None

        @property
        def is_connected(self) -> bool:
            return self._thread is not None

        @staticmethod
        def find_cameras() -> list[dict[str, Any]]:
            return []

        def connect(self, warmup: bool = True) -> None:
            self._thread = threading.Thread(target=self._run, name="scene-sim", daemon=True)
            self._thread.start()

        def _run(self) -> None:
            period, t0 = 1.0 / self.config.fps, time.monotonic()
            k = 0
            while not self._stop.is_set():
                time.sleep(max(t0 + k * period - time.monotonic(), 0.0))
                frame = np.full((self.config.height, self.config.width, 3), 40, dtype=np.uint8)
                frame[0, 0, :] = (k & 255, (k >> 8) & 255, (k >> 16) & 255)
                with self._cond:
                    self._frame, self._fresh = frame, True
                    self.delivered += 1
                    self._cond.notify_all()
                k += 1

        def async_read(self, timeout_ms: float = 200) -> np.ndarray:
            with self._cond:
                if not self._cond.wait_for(lambda: self._fresh, timeout_ms / 1000):
                    raise TimeoutError(f"scene camera: no new frame within {timeout_ms} ms")
                self._fresh = False
                assert self._frame is not None
                return self._frame

        def read(self, color_mode: object = None) -> np.ndarray:
            return self.async_read(1000)

        def disconnect(self) -> None:
            self._stop.set()
            if self._thread is not None:
                self._thread.join(2.0)
            self._thread = None

    # LeRobot makes a camera from its config's module by name (SceneSimConfig -> SceneSim): give both a module
    module = types.ModuleType("optitac_scene_sim")
    for cls in (SceneSimConfig, SceneSim):
        cls.__module__, cls.__qualname__ = module.__name__, cls.__name__
        setattr(module, cls.__name__, cls)
    sys.modules[module.__name__] = module
    return SceneSimConfig, SceneSim


def _alive(pid: int | None) -> bool:
    """A process ``pid`` still exists (None: there was none)."""
    if pid is None:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def run(seconds: float, workdir: Path, sensor_fps: float = 240.0, fps: int = 30,
        process: bool = True) -> dict[str, Any]:
    """Record ``seconds`` at ``fps``; the counts (see the module's description)."""
    from lerobot.cameras.utils import make_cameras_from_configs  # noqa: F401 - the camera registry, first
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.datasets.utils import build_dataset_frame, hw_to_dataset_features
    from lerobot.robots.config import RobotConfig
    from lerobot.robots.utils import make_robot_from_config
    from lerobot.utils.import_utils import register_third_party_plugins

    register_third_party_plugins()
    scene_config, _ = _scene_camera_classes()
    before = set(threading.enumerate())
    config_class = RobotConfig.get_choice_class("optitac")
    camera_config = type(config_class().tactile)
    config = config_class(tactile=camera_config(fps=fps, sensor_fps=sensor_fps, process=process),
                          cameras={"scene": scene_config(fps=fps)})
    robot = make_robot_from_config(config)
    robot.connect()
    features = hw_to_dataset_features(robot.observation_features, "observation", use_video=True)
    cameras = sum(1 for v in robot.observation_features.values() if isinstance(v, tuple))
    dataset = LeRobotDataset.create("optitac/record-check", fps, features, root=workdir / "dataset",
                                    robot_type=robot.name, use_videos=True,
                                    image_writer_threads=4 * cameras)  # lerobot-record's default: 4 a camera
    scene = robot.cameras["scene"]
    start = robot.status()
    scene_start = scene.delivered
    recorded_stamps, sensor_frames = [], []
    t_next = time.perf_counter()
    for _ in range(round(seconds * fps)):
        obs = robot.get_observation()
        frame = build_dataset_frame(dataset.features, obs, prefix="observation")
        dataset.add_frame({**frame, "task": "touch"})
        pixel = obs["scene"][0, 0]
        recorded_stamps.append(int(pixel[0]) | int(pixel[1]) << 8 | int(pixel[2]) << 16)
        sensor_frames.append(int(obs["optitac.frame"]))
        t_next += 1.0 / fps
        time.sleep(max(t_next - time.perf_counter(), 0.0))
    end = robot.status()
    scene_end = scene.delivered
    child = getattr(robot.tactile.sensor, "pid", None)  # the sensor's process (process=True)
    robot.disconnect()
    # the plugins' threads (the sensor's reader and its simulated camera's renderer) and the scene camera's; not
    # LeRobot's image writers (stopped with the dataset) nor tqdm's monitor
    left = [t.name for t in set(threading.enumerate()) - before
            if t.is_alive() and t.name.startswith(("optitac", "scene-sim"))]
    dataset.save_episode()
    dataset.finalize()
    first, last = recorded_stamps[0], recorded_stamps[-1]
    return {
        "ticks": len(recorded_stamps), "dataset_frames": dataset.meta.total_frames,
        "scene_delivered": scene_end - scene_start, "scene_recorded": len(set(recorded_stamps)),
        "scene_missed": (last - first + 1) - len(set(recorded_stamps)),
        "sensor_read": end.frames - start.frames, "sensor_dropped": end.dropped - start.dropped,
        "sensor_in_dataset": len(set(sensor_frames)), "sensor_unread": end.unread - start.unread,
        "sensor_frame_span": sensor_frames[-1] - sensor_frames[0] + 1, "threads_left": len(left),
        "threads": ", ".join(sorted(left)), "process": child, "process_left": _alive(child),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--sensor-fps", type=float, default=240.0)
    p.add_argument("--fps", type=int, default=30)
    p.add_argument("--workdir", type=Path, required=True, help="where the dataset is written (new)")
    p.add_argument("--in-process", action="store_true",
                   help="the sensor in LeRobot's process (the camera plugin's process=False)")
    args = p.parse_args(argv)
    if args.workdir.exists():
        p.error(f"--workdir {args.workdir}: exists (give a new directory)")
    args.workdir.mkdir(parents=True)
    c = run(args.seconds, args.workdir, args.sensor_fps, args.fps, process=not args.in_process)
    print(f"dataset: {c['dataset_frames']} frames at {args.fps} fps ({c['ticks']} ticks)")
    print(f"scene camera: {c['scene_delivered']} frames delivered, {c['scene_recorded']} recorded, "
          f"{c['scene_missed']} missed")
    print(f"optitac: {c['sensor_read']} frames read at {args.sensor_fps:g} fps, {c['sensor_dropped']} dropped by its "
          f"camera; {c['sensor_in_dataset']} in the dataset (the newest at each tick), {c['sensor_unread']} counted "
          f"unread")
    where = "LeRobot's process" if c["process"] is None else f"process {c['process']}"
    print(f"the sensor read in {where}; left after disconnect: {'yes' if c['process_left'] else 'no'}")
    print(f"threads left after disconnect: {c['threads_left']} {c['threads']}".rstrip())
    lost = c["scene_missed"] or c["sensor_dropped"] or c["dataset_frames"] != c["ticks"] or c["threads_left"] or c["process_left"]
    return 1 if lost else 0


if __name__ == "__main__":
    sys.exit(main())
