"""``drivebench/LaneFollow-v0``: a Gymnasium environment whose every step is one lock-step step of the real stack.

The simulator, the noise injector and the scorer run as processes over Zenoh, as in ``drivebench run``; the
environment takes the brain's place (frames in, commands out). The stack starts at the first ``reset`` and serves
every later episode; ``router=`` joins a stack that is already running (this machine or another) instead.
"""

from __future__ import annotations

import fnmatch
import shutil
import tempfile
import threading
import uuid
import weakref
from pathlib import Path
from typing import Any

import gymnasium as gym
import msgspec
import numpy as np
from gymnasium import spaces

from brains.lane_policy.features import FEATURES, line_features, scaled
from circuits import Circuit, CircuitError, load_circuit
from drivebench.rl.link import BrainLink, Transition, ending
from drivebench.rl.options import GENERATED, check_render_threads, env_options, start_m_option
from drivebench.rl.reward import ProgressReward
from drivebench.rl.stack import StackError, open_stack
from protocol.bus_config import BusError, probe_router
from protocol.episode_spec import EpisodeSpec
from protocol.messages import EndReason

FIRST_FRAME_TIMEOUT_S = 120.0  # a new circuit's scene is built before its first frame (seconds with PyBullet)
STEP_TIMEOUT_S = 60.0
SCORE_TIMEOUT_S = 10.0
STOP_TIMEOUT_S = 30.0
CIRCUITS_KEPT = 16
RESET_OPTIONS = ("circuit", "variation_index", "start_m")


class LaneFollowEnv(gym.Env):
    """Follow the lane of a drivebench circuit, one lock-step step of the real stack per ``step``.

    Action: ``Box([-1, -1], [1, 1])``, mapped linearly onto (speed in ``speed_range_mps`` m/s, yaw rate in
    ``yaw_rate_range_radps`` rad/s, positive = left). An action outside the box, NaN or of the wrong shape raises
    ValueError and sends nothing.

    Observation (``observation=``): ``"image"``, the brain's camera frame (H x W x 3 uint8, the noise injector's
    when ``noise`` is set); ``"image+state"``, a dict of that image, ``speed_mps`` (the commanded speed) and
    ``previous_action``; ``"features"``, the 10 line features of ``brains.lane_policy.features`` (float32 in [-1,1]).

    Reward per step (``drivebench.rl.reward``): metres of progress along the centreline times
    ``max(0, 1 - |lateral offset| / road half width)``, minus ``smoothness * ||action - previous action||^2``, minus
    ``crash_penalty`` on the step that ends the episode by touching a wall or leaving the road.

    ``terminated``: crash, off track, or the lap target (``laps``) reached. ``truncated``: ``max_episode_s`` of
    simulated time passed (or the stack cut the episode short). ``info``: progress, lateral offset, simulated time
    and the command every step, and where the episode started (``start_m``); with ``live_metrics=True`` (off by
    default) the scorer's newest live metrics of this episode (they arrive on wall-clock time, one or more steps
    late, so with them the same seed and actions no longer give the same info: Gymnasium's ``check_env`` fails);
    at the end ``end_reason`` and ``score``, the scorer's metrics of the episode (the same as
    ``drivebench run``'s).

    ``reset(seed=...)`` draws the circuit (from the ``circuit`` list; ``"random:*"``, ``"twisty:*"`` or
    ``"grandprix:*"`` in it is a new generated circuit each time it is drawn), the variation (from the ``variation``
    list) and the episode seed (which seeds the noise) from ``seed``;
    ``options={"circuit": ..., "variation_index": ...}`` choose them instead. Where the car starts
    (``EpisodeSpec.start_m``, metres along the circuit in driving order): ``start="line"``, the start line (or a
    variation's ``start_m``); ``start="random"``, drawn uniformly over the circuit's length from ``seed`` too;
    ``options={"start_m": ...}`` chooses it (a ValueError naming the circuit's length when it is not on the
    circuit). The reward's progress, and the lap target, count from there.

    ``render_threads``: llvmpipe threads of the environment's own simulator (renderer "gl"): 1, since a vector env
    runs a stack per environment; one environment alone on a machine may take its cores (same frames, faster).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(
        self,
        *,
        circuit: str | list[str] = "simple",
        variation: str | list[str] = "",
        noise: str | list | tuple = (),
        camera: Any = (320, 240),
        renderer: str = "pybullet",
        observation: str = "image",
        start: str = "line",
        speed_range_mps: tuple[float, float] = (0.0, 10.0),
        yaw_rate_range_radps: tuple[float, float] = (-2.0, 2.0),
        laps: int = 1,
        max_episode_s: float = 120.0,
        step_s: float = 0.05,
        smoothness: float = 0.1,
        crash_penalty: float = 10.0,
        live_metrics: bool = False,
        router: str | None = None,
        run_id: str | None = None,
        step_timeout_s: float = 600.0,
        startup_timeout_s: float = 60.0,
        render_mode: str | None = None,
        render_threads: int = 1,
    ):
        self.options = env_options(
            circuit=circuit,
            variation=variation,
            noise=noise,
            camera=camera,
            renderer=renderer,
            observation=observation,
            start=start,
            speed_range_mps=speed_range_mps,
            yaw_rate_range_radps=yaw_rate_range_radps,
            laps=laps,
            max_sim_seconds=max_episode_s,
            step_s=step_s,
            brain_timeout_s=step_timeout_s,
        )
        check_render_threads(render_threads, router=router)
        self.render_threads = render_threads
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if router is not None:
            try:  # a plain TCP probe, no bus session: a vector env makes one environment in its parent process
                probe_router(router.split(",")[0].strip(), timeout_s=5.0)
            except BusError as error:
                raise ConnectionError(f"router={router!r}: {error}") from None
        self.render_mode = render_mode
        self.router, self.startup_timeout_s = router, startup_timeout_s
        self.run_id = run_id or ("default" if router else f"gym-{uuid.uuid4().hex[:8]}")
        self.name = f"gym-{uuid.uuid4().hex[:8]}"
        self.smoothness, self.crash_penalty, self.live_metrics = smoothness, crash_penalty, live_metrics
        self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.observation_space = self._observation_space()
        self._parts: dict[str, Any] = {}  # stack, link, run_dir: made at the first reset, ended by close()
        self._finalizer = weakref.finalize(self, _close_parts, self._parts)
        _UNCLOSED.add(self._finalizer)
        self._circuits: dict[tuple[str, str], Circuit] = {}
        self._episode: int | None = None
        self._running = False

    def _observation_space(self) -> spaces.Space:
        camera = self.options.specs[0].camera
        image = spaces.Box(0, 255, shape=(camera.height_px, camera.width_px, 3), dtype=np.uint8)
        if self.options.observation == "features":
            return spaces.Box(-1.0, 1.0, shape=(FEATURES,), dtype=np.float32)
        if self.options.observation == "image+state":
            low, high = self.options.speed_range_mps
            return spaces.Dict(
                {
                    "image": image,
                    "speed_mps": spaces.Box(low, high, shape=(1,), dtype=np.float32),
                    "previous_action": spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32),
                }
            )
        return image

    # -- the stack --

    def _ensure_stack(self) -> BrainLink:
        if "link" in self._parts:
            return self._parts["link"]
        if self._finalizer.alive is False:
            raise RuntimeError("this environment was closed; make a new one")
        run_dir = Path(tempfile.mkdtemp(prefix=f"drivebench-{self.run_id}-"))
        self._parts["run_dir"] = run_dir
        try:
            stack = open_stack(
                router=self.router,
                run_id=self.run_id,
                run_dir=run_dir,
                startup_timeout_s=self.startup_timeout_s,
                render_threads=self.render_threads,
            )
        except (StackError, BusError) as error:
            raise ConnectionError(str(error)) from None
        self._parts["stack"] = stack
        assert stack.bus is not None
        perturbed = any(spec.noise for spec in self.options.specs)
        link = BrainLink(stack.bus, run_id=self.run_id, name=self.name, perturbed=perturbed, check=stack.raise_failure)
        self._parts["link"] = link
        return link

    def _circuit(self, spec: EpisodeSpec) -> Circuit:
        key = (spec.circuit, spec.direction)
        if len(self._circuits) > CIRCUITS_KEPT:  # generated circuits: a new one nearly every episode
            self._circuits.clear()
        if key not in self._circuits:
            self._circuits[key] = load_circuit(spec.circuit, direction=spec.direction)
        return self._circuits[key]

    # -- Gymnasium API --

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        spec = self._episode_spec(options or {})
        link = self._ensure_stack()
        self._end_running(link)
        stack = self._parts["stack"]
        self._episode = stack.begin(spec)
        self._running = True
        link.follow(self._episode)
        self._spec = spec
        first = link.wait(0, timeout_s=FIRST_FRAME_TIMEOUT_S)
        self._reward = ProgressReward(
            self._circuit(spec), smoothness=self.smoothness, crash_penalty=self.crash_penalty, start_m=spec.start_m
        )
        self._previous_action = np.zeros(2, np.float32)
        self._speed_mps = 0.0
        self._last = first
        return self._observation(first), self._step_info(first, None)

    def _episode_spec(self, options: dict[str, Any]) -> EpisodeSpec:
        unknown = set(options) - set(RESET_OPTIONS)
        if unknown:
            raise ValueError(f"reset options: unknown {sorted(unknown)} (known: {', '.join(RESET_OPTIONS)})")
        circuits, specs = self.options.circuits, self.options.specs
        circuit = circuits[int(self.np_random.integers(len(circuits)))]
        index = int(self.np_random.integers(len(specs)))
        seed = int(self.np_random.integers(2**31 - 1))
        generated_seed = int(self.np_random.integers(1_000_000))
        # Drawn whatever the options say, so that they change no other draw; only with start="random", so that the
        # draws of an environment that starts at the line are the ones they always were.
        start_fraction = float(self.np_random.random()) if self.options.start == "random" else None
        circuit = options.get("circuit", circuit)
        if not any(circuit == name or fnmatch.fnmatchcase(circuit, name) for name in circuits):
            raise ValueError(f"reset options: circuit {circuit!r} is not one of this environment's {list(circuits)}")
        if circuit in GENERATED:
            circuit = circuit.replace("*", str(generated_seed))
        index = options.get("variation_index", index)
        if not isinstance(index, int) or not 0 <= index < len(specs):
            raise ValueError(f"reset options: variation_index must be an int within 0..{len(specs) - 1}, got {index!r}")
        spec = msgspec.structs.replace(specs[index], circuit=circuit, seed=seed, active_brain=self.name)
        return msgspec.structs.replace(spec, start_m=self._start_m(spec, options, start_fraction))

    def _start_m(self, spec: EpisodeSpec, options: dict[str, Any], start_fraction: float | None) -> float:
        """Where the episode's car starts: the option, else the draw, else the spec's own (a variation's)."""
        circuit = self._circuit(spec)
        if "start_m" in options:
            return start_m_option(options["start_m"], circuit)
        if start_fraction is not None:
            return (start_fraction * circuit.length_m) % circuit.length_m  # % : a product rounded up to the length
        try:
            circuit.check_start_m(spec.start_m)
        except CircuitError as error:  # a variation's start_m beyond this circuit's length
            raise ValueError(f"variation start_m: {error}") from None
        return spec.start_m

    def _end_running(self, link: BrainLink) -> None:
        """Stop the episode still running (a reset before its end) and wait for its END."""
        if self._running and not link.ended():
            self._parts["stack"].stop_episode()
            link.wait_end(timeout_s=STOP_TIMEOUT_S)
        self._running = False

    def step(self, action):
        action = self._checked_action(action)
        if not self._running:
            raise RuntimeError("step() before reset(), or after the episode ended: call reset()")
        link: BrainLink = self._parts["link"]
        speed_mps = scaled(action[0], *self.options.speed_range_mps)
        yaw_rate_radps = scaled(action[1], *self.options.yaw_rate_range_radps)
        link.answer(
            self._last.seq, stamp_ns=self._last.pose.header.stamp_ns, speed_mps=speed_mps, yaw_rate_radps=yaw_rate_radps
        )
        outcome = link.wait(self._last.seq + 1, timeout_s=STEP_TIMEOUT_S)
        crashed = outcome.end is not None and outcome.end.reason in (EndReason.CRASH, EndReason.OFF_TRACK)
        terms = self._reward.step(
            x_m=outcome.pose.x_m,
            y_m=outcome.pose.y_m,
            action=action,
            previous_action=self._previous_action,
            crashed=crashed,
        )
        terminated, truncated = ending(outcome.end)
        self._previous_action, self._speed_mps = action, speed_mps
        if outcome.image is None:  # the episode's end: no frame after the last step; the last image stands
            outcome = Transition(image=self._last.image, pose=outcome.pose, seq=outcome.seq, end=outcome.end)
        self._last = outcome
        info = self._step_info(outcome, terms)
        if outcome.end is not None:
            self._running = False
            info["end_reason"] = str(outcome.end.reason)
            score = link.score(self._episode, timeout_s=SCORE_TIMEOUT_S)
            info["score"] = None if score is None else msgspec.to_builtins(score.metrics)
        return self._observation(outcome), float(terms.reward), terminated, truncated, info

    def _checked_action(self, action) -> np.ndarray:
        try:
            array = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"action must be 2 numbers in [-1, 1], got {action!r}") from None
        if array.shape != (2,):
            raise ValueError(f"action must have shape (2,), got shape {array.shape}: {action!r}")
        if not np.all(np.isfinite(array)):
            raise ValueError(f"action must be finite, got {action!r}")
        if np.any(np.abs(array) > 1.0):
            raise ValueError(f"action must lie in [-1, 1] (the action space), got {action!r}")
        return array.astype(np.float32)

    def _observation(self, outcome: Transition):
        image = np.array(outcome.image, dtype=np.uint8)  # a copy: the caller may keep or change it
        if self.options.observation == "features":
            return line_features(image, previous_action=self._previous_action)
        if self.options.observation == "image+state":
            return {
                "image": image,
                "speed_mps": np.array([self._speed_mps], np.float32),
                "previous_action": np.array(self._previous_action, np.float32),
            }
        return image

    def _step_info(self, outcome: Transition, terms) -> dict[str, Any]:
        info: dict[str, Any] = {
            "run_id": self.run_id,
            "circuit": self._spec.circuit,
            "start_m": self._spec.start_m,
            "seq": outcome.seq,
            "sim_time_s": outcome.pose.header.stamp_ns / 1e9,
            "x_m": outcome.pose.x_m,
            "y_m": outcome.pose.y_m,
            "yaw_rad": outcome.pose.yaw_rad,
            "progress_m": self._reward.progress_m if terms is not None else 0.0,
            "lateral_m": terms.lateral_m if terms is not None else 0.0,
            "speed_mps": outcome.pose.speed_mps,
            "yaw_rate_radps": outcome.pose.yaw_rate_radps,
        }
        if self.live_metrics and (live := self._parts["link"].latest_live()) is not None:
            info["live_metrics"] = msgspec.to_builtins(live)
        return info

    def render(self):
        if self.render_mode != "rgb_array" or getattr(self, "_last", None) is None:
            return None
        return np.array(self._last.image, dtype=np.uint8)

    def close(self):
        """Stop the stack's processes (a local stack) or leave the run (``router=``); safe to call again."""
        self._running = False
        self._finalizer()
        _UNCLOSED.discard(self._finalizer)


# The finalizers of environments not closed yet. weakref.finalize would close them at exit, but too late: Python
# first waits for every non-daemon thread, and Zenoh's callback threads of an open session (non-daemon, as the thread
# that made the session was) end only when the session closes, so a script that ends, or dies of an exception, without
# env.close() hung for ever. Closed here instead, before that wait (the hook concurrent.futures uses too).
_UNCLOSED: set[weakref.finalize] = set()


def _close_unclosed_environments() -> None:
    for finalizer in list(_UNCLOSED):
        finalizer()
    _UNCLOSED.clear()


threading._register_atexit(_close_unclosed_environments)  # type: ignore[attr-defined]


def _close_parts(parts: dict[str, Any]) -> None:
    """End what an environment made: its brain link, its stack (every process of a local one), its run folder."""
    link, stack, run_dir = parts.pop("link", None), parts.pop("stack", None), parts.pop("run_dir", None)
    try:
        if link is not None:
            link.close()
    finally:
        if stack is not None:
            stack.close()
        if run_dir is not None:
            shutil.rmtree(run_dir, ignore_errors=True)
