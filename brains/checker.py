"""The brain checker: does a brain meet the contract the brain host relies on? (``drivebench brains check``)

Like Gymnasium's ``check_env``, it runs the brain outside any stack, on real rendered frames, and says per check
what passed and, for what did not, how to fix it. The checks, in order (a failed ``make`` stops the rest):

make          the name resolves and the brain is built with the given options
protocol      ``reset(*, seed)`` and ``act(observation)`` exist
act           ``act`` answers real frames of several worlds with an ``Action`` of two finite floats
units         speeds look like m/s and yaw rates like rad/s (not km/h, not degrees)
read-only     ``act`` does not write into the image (the host hands it a read-only view of the message)
answer time   time per frame: under 50 ms keeps real-time runs at 20 Hz; over the lock-step timeout ends episodes
determinism   the same frames after ``reset(seed=1)`` give the same actions, after other frames and in a new brain
memory        memory does not grow over a few hundred frames (a brain must not keep every frame)

The contract tests in ``tests/test_brain_contract.py`` run this over every registered brain.

A slow brain takes minutes here (the checks act on ~700 frames): :func:`iter_checks` reports progress and yields
each result as it is known (an interrupted check still shows those), and once the answer times already fail the
answer-time check whatever the remaining frames take, it stops acting and skips the checks after it.
"""

from __future__ import annotations

import math
import os
import statistics
import time
import tracemalloc
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from brains.base import Action, GroundTruth, Observation
from brains.registry import BrainOptionsError, UnknownBrainError, make_brain, resolve
from brains.sandbox_exit import exit_for

REALTIME_BUDGET_S = 0.05  # one frame at 20 Hz (Behavior Metrics' control period)
LOCKSTEP_TIMEOUT_S = 10.0  # EpisodeSpec.brain_timeout_s's default: slower answers end lock-step episodes
MAX_SPEED_MPS = 40.0  # F1 cars here drive up to ~24 m/s; far beyond that it is km/h or a bug
MAX_YAW_RATE_RADPS = 2 * math.pi  # a turn a second; beyond it it is degrees per second or a bug
MEMORY_GROWTH_LIMIT_BYTES = 20 * 2**20  # ~90 raw 320x240 frames: what keeping every frame costs in 300 steps
STEP_NS = 50_000_000
ANSWER_PERCENTILE = 95  # the answer-time check judges this percentile of the time per frame
PROGRESS_EVERY_S = 2.0  # how often a slow stage says how far it got

Progress = Callable[[str], None]  # told what a stage is doing (one short line), at most every PROGRESS_EVERY_S

# Worlds the frames are rendered in: the paper's default, its white line, no line on a white road, and no sun.
CHECK_WORLDS: tuple[dict[str, Any], ...] = (
    {},
    {"line": "white"},
    {"line": "none", "road": "white"},
    {"lighting": "no_sun"},
)


@dataclass(frozen=True)
class Check:
    """One check's outcome. status: "pass", "warn" (works, with a caveat), "fail" (the host will misbehave) or "skip"
    (not run: an earlier check already failed). wall: when the brain's own error is what a sandbox's wall raises
    (``brains.sandbox_exit``: ``memory``, ``processes``, ``file_size``, ``refused``), its name, else empty; a check
    run inside a sandbox (a challenge's) is typed by it, never by the detail's words."""

    name: str
    status: str
    detail: str
    fix: str = ""
    wall: str = ""

    def line(self) -> str:
        text = f"{self.status.upper():4}  {self.name:<12} {self.detail}"
        return text + (f"\n      fix: {self.fix}" if self.fix else "")


@dataclass(frozen=True)
class Frame:
    """A rendered camera frame (H x W x 3 uint8 RGB) and the pose it was taken from."""

    image_rgb: np.ndarray
    truth: GroundTruth


def render_frames(
    *,
    circuit: str = "simple",
    worlds: Iterable[dict[str, Any]] = CHECK_WORLDS,
    frames_per_world: int = 12,
    spacing_m: float = 0.4,
    camera_wh: tuple[int, int] = (320, 240),
) -> list[Frame]:
    """Consecutive frames along ``circuit``'s centreline (0.4 m apart: 8 m/s at 20 Hz) in each world, rendered."""
    from circuits import load_circuit
    from protocol.episode_spec import CameraSpec, WorldVariation
    from services.simulator.car import CarState
    from services.simulator.scene import Scene

    track = load_circuit(circuit)
    camera = CameraSpec(width_px=camera_wh[0], height_px=camera_wh[1])
    frames = []
    for world in worlds:
        with Scene.for_world(track, WorldVariation(**world)) as scene:
            for step in range(frames_per_world):
                x, y, yaw = track.centreline.pose_at(10.0 + spacing_m * step)
                rendered = scene.render(CarState(x_m=x, y_m=y, yaw_rad=yaw), camera)
                # As the host hands it over: a view of the message's bytes, which no brain can make writeable (an
                # array that owns its memory could be: setflags(write=True), then writing into the checker's frame).
                image = np.frombuffer(rendered.tobytes(), dtype=np.uint8).reshape(rendered.shape)
                frames.append(Frame(image, GroundTruth(x_m=x, y_m=y, yaw_rad=yaw, circuit=circuit)))
    return frames


def check_brain(
    name: str,
    *,
    options: dict[str, Any] | None = None,
    frames: list[Frame] | None = None,
    memory_steps: int = 300,
    brain_timeout_s: float = LOCKSTEP_TIMEOUT_S,
) -> list[Check]:
    """Run every check on brain ``name`` built with ``options``; one :class:`Check` per check, in order."""
    return list(
        iter_checks(name, options=options, frames=frames, memory_steps=memory_steps, brain_timeout_s=brain_timeout_s)
    )


def iter_checks(
    name: str,
    *,
    options: dict[str, Any] | None = None,
    frames: list[Frame] | None = None,
    memory_steps: int = 300,
    brain_timeout_s: float = LOCKSTEP_TIMEOUT_S,
    progress: Progress | None = None,
) -> Iterator[Check]:
    """:func:`check_brain`, one :class:`Check` at a time as each is known; ``progress`` hears how far a stage got.
    brain_timeout_s: the lock-step timeout of the runs the brain is meant for (answers slower end episodes)."""
    options = dict(options or {})
    say = _Throttled(progress)
    say("make: building the brain", now=True)
    try:
        origin = resolve(name).origin
        brain = make_brain(name, **options)
    except (UnknownBrainError, BrainOptionsError) as error:
        yield Check("make", "fail", str(error), "check the name (drivebench brains list) and its options")
        return
    except Exception as error:  # the user's constructor: whatever it raises, report it as one line
        yield Check(
            "make",
            "fail",
            f"building it raised {type(error).__name__}: {error}",
            "the constructor must accept the options given (keyword arguments) and load what it needs",
            wall=_wall(error),
        )
        return
    yield Check("make", "pass", f"{type(brain).__name__} from {name} ({origin})")
    yield (protocol := _check_protocol(brain))
    if protocol.status == "fail":
        return
    if frames is None:
        say(f"rendering {len(CHECK_WORLDS)} worlds of simple", now=True)
        frames = render_frames()
    stage = _check_act(brain, frames, brain_timeout_s=brain_timeout_s, say=say)
    yield from stage.checks
    if stage.answers is None:
        return
    yield _check_units(stage.answers.actions)
    yield _check_answer_time(stage.answers.seconds, brain_timeout_s=brain_timeout_s, total=len(frames))
    if stage.stopped:
        skipped = f"not run: at over {brain_timeout_s:g} s a frame, the answer-time check failed (see above)"
        yield Check("determinism", "skip", skipped)
        yield Check("memory", "skip", skipped)
        return
    yield _check_determinism(brain, lambda: make_brain(name, **options), frames, stage.answers.actions, say=say)
    yield _check_memory(brain, frames, steps=memory_steps, say=say)


class _Throttled:
    """Passes a progress line on at most every PROGRESS_EVERY_S (``now``: at once, for a new stage)."""

    def __init__(self, progress: Progress | None):
        self._progress = progress
        self._last = -math.inf

    def __call__(self, text: str, *, now: bool = False) -> None:
        if self._progress is None or (not now and time.monotonic() - self._last < PROGRESS_EVERY_S):
            return
        self._last = time.monotonic()
        self._progress(text)


def passed(results: list[Check]) -> bool:
    return all(result.status != "fail" for result in results)


# -- the checks ------------------------------------------------------------------------------------------------------


def _check_protocol(brain: Any) -> Check:
    missing = [method for method in ("reset", "act") if not callable(getattr(brain, method, None))]
    if missing:
        return Check(
            "protocol",
            "fail",
            f"no {' and no '.join(missing)} method",
            "implement reset(self, *, seed: int) and act(self, observation) -> Action (brains.base.Brain)",
        )
    try:
        brain.reset(seed=0)
    except TypeError as error:
        return Check(
            "protocol",
            "fail",
            f"reset(seed=0) raised TypeError: {error}",
            "reset takes the seed as a keyword argument: def reset(self, *, seed: int) -> None",
        )
    except Exception as error:
        return Check(
            "protocol",
            "fail",
            f"reset(seed=0) raised {type(error).__name__}: {error}",
            "reset must put the brain back to its start state without failing",
            wall=_wall(error),
        )
    return Check("protocol", "pass", "reset(seed=...) and act(observation)")


@dataclass(frozen=True)
class _Answers:
    """What a brain answered in order: (speed, yaw rate) per frame and the seconds each answer took."""

    actions: list[tuple[float, float]]
    seconds: list[float]


@dataclass
class _ActStage:
    checks: list[Check]
    answers: _Answers | None = None  # None: act failed, so nothing further is checked
    stopped: bool = False  # cut short: the answer times already fail the answer-time check


def _drive(
    brain: Any,
    frames: list[Frame],
    *,
    seed: int,
    say: Callable[[str], None] = lambda text: None,
    what: str = "",
    enough: Callable[[list[float]], bool] = lambda seconds: False,
) -> tuple[list[tuple[float, float]], list[float]]:
    """Reset with ``seed`` and act on frames in order: (speed, yaw rate) per frame and the seconds each took; until
    ``enough(seconds so far)`` or the last frame. ``say`` hears ``what`` and how far it got."""
    brain.reset(seed=seed)
    truth = getattr(brain, "needs_ground_truth", False)
    actions: list[tuple[float, float]] = []
    seconds: list[float] = []
    for seq, frame in enumerate(frames):
        observation = Observation(
            image_rgb=frame.image_rgb, stamp_ns=seq * STEP_NS, seq=seq, ground_truth=frame.truth if truth else None
        )
        started = time.perf_counter()
        try:
            action = brain.act(observation)
        except ValueError as error:
            if _answers_a_writeable_copy(brain, observation):
                raise _WroteIntoImage(error) from None
            raise
        seconds.append(time.perf_counter() - started)
        actions.append(_as_pair(action))
        say(f"{what}: frame {seq + 1}/{len(frames)}, {seconds[-1]:.2f} s for the last")
        if enough(seconds):
            break
    return actions, seconds


def answer_time_fails(seconds: list[float], *, total: int, brain_timeout_s: float) -> bool:
    """Whether the answer times of the first frames already fail the answer-time check over ``total`` frames, however
    fast the rest are: enough of them are over the timeout that the percentile is, whatever else comes."""
    slow = sum(value > brain_timeout_s for value in seconds)
    rank = math.floor(ANSWER_PERCENTILE / 100 * (total - 1))  # np.percentile interpolates from this sorted index up
    return slow >= total - rank


class _BadAction(Exception):
    pass


class _WroteIntoImage(Exception):
    """act failed on the read-only camera image and answered a writeable copy of it: it writes into the image."""

    def __init__(self, error: ValueError):
        super().__init__(str(error))
        self.error = error


def _answers_a_writeable_copy(brain: Any, observation: Observation) -> bool:
    """Whether ``act``, having raised on ``observation``, answers the same observation with a writeable copy of its
    image: then the read-only view is what it tripped on. Decided by what act does, never by the error's words (a
    brain's own ValueError may say anything); the brain is not driven further after this."""
    if observation.image_rgb.flags.writeable:
        return False  # it raised on a writeable image: writing into it is not what failed
    copy = Observation(
        image_rgb=observation.image_rgb.copy(),
        stamp_ns=observation.stamp_ns,
        seq=observation.seq,
        ground_truth=observation.ground_truth,
    )
    try:
        brain.act(copy)
    except Exception:  # the user's act, failing again: its error is not the image's (the first one is reported)
        return False
    return True


def _as_pair(action: Any) -> tuple[float, float]:
    if not isinstance(action, Action):
        raise _BadAction(f"act returned {type(action).__name__}, not brains.base.Action")
    try:
        pair = (float(action.speed_mps), float(action.yaw_rate_radps))
    except (TypeError, ValueError) as error:
        raise _BadAction(f"Action fields are not numbers ({error})") from None
    if not all(math.isfinite(value) for value in pair):
        raise _BadAction(f"act returned a non-finite command {pair}")
    return pair


def _check_act(brain: Any, frames: list[Frame], *, brain_timeout_s: float, say: Callable[..., None]) -> _ActStage:
    say("act: the first frame", now=True)
    try:
        actions, seconds = _drive(
            brain,
            frames,
            seed=1,
            say=say,
            what="act",
            enough=lambda seconds: answer_time_fails(seconds, total=len(frames), brain_timeout_s=brain_timeout_s),
        )
    except _BadAction as error:
        return _ActStage(
            [Check("act", "fail", str(error), "return Action(speed_mps=float, yaw_rate_radps=float), both finite")]
        )
    except _WroteIntoImage as wrote:
        return _ActStage(
            [
                Check("act", "pass", "answered frames until it wrote into one"),
                Check(
                    "read-only",
                    "fail",
                    f"act wrote into the camera image: it raised {type(wrote.error).__name__} ({wrote.error}) on "
                    "the read-only image and answered a writeable copy of it",
                    "copy the image before drawing on it: image = observation.image_rgb.copy()",
                ),
            ]
        )
    except Exception as error:
        return _ActStage([_raised("act", error)])
    sizes = sorted({f"{f.image_rgb.shape[1]}x{f.image_rgb.shape[0]}" for f in frames})
    stopped = len(actions) < len(frames)
    answered = f"{len(actions)} of {len(frames)}" if stopped else f"{len(frames)}"
    return _ActStage(
        [
            Check(
                "act",
                "pass",
                f"{answered} frames of {len(CHECK_WORLDS)} worlds ({', '.join(sizes)}) answered with finite Actions"
                + (" (stopped early: see answer time)" if stopped else ""),
            ),
            Check("read-only", "pass", "the camera image was left untouched"),
        ],
        answers=_Answers(actions=actions, seconds=seconds),
        stopped=stopped,
    )


def _raised(name: str, error: Exception) -> Check:
    return Check(
        name,
        "fail",
        f"act raised {type(error).__name__}: {error}",
        "act must answer any 320x240 RGB frame (uint8, H x W x 3) without raising",
        wall=_wall(error),
    )


def _wall(error: BaseException) -> str:
    """The sandbox wall ``error`` is (a name of ``brains.sandbox_exit.SandboxExit``, lower case), or empty."""
    wall = exit_for(error)
    return wall.name.lower() if wall is not None else ""


def _check_units(actions: list[tuple[float, float]]) -> Check:
    speeds = [abs(speed) for speed, _ in actions]
    yaw_rates = [abs(yaw_rate) for _, yaw_rate in actions]
    detail = f"speed up to {max(speeds):.2f} m/s, |yaw rate| up to {max(yaw_rates):.2f} rad/s"
    if max(speeds) > MAX_SPEED_MPS:
        return Check("units", "fail", detail, "speed_mps is metres per second (km/h / 3.6)")
    if max(yaw_rates) > MAX_YAW_RATE_RADPS:
        return Check(
            "units", "fail", detail, "yaw_rate_radps is radians per second (degrees * pi / 180), positive turning left"
        )
    if max(speed for speed, _ in actions) <= 0.0:
        return Check("units", "warn", detail + "; it never drives forward on the road", "")
    return Check("units", "pass", detail)


def _check_answer_time(seconds: list[float], *, brain_timeout_s: float, total: int) -> Check:
    p50, p95 = statistics.median(seconds), float(np.percentile(seconds, ANSWER_PERCENTILE))
    detail = f"p50 {1e3 * p50:.2f} ms, p95 {1e3 * p95:.2f} ms per frame"
    fix = "answer faster, or raise the episode's brain_timeout_s (run --brain-timeout)"
    if len(seconds) < total:
        slow = sum(value > brain_timeout_s for value in seconds)
        return Check(
            "answer time",
            "fail",
            f"{slow} of the first {len(seconds)} frames took over the lock-step timeout of {brain_timeout_s:g} s, "
            f"too many for the p95 of {total} frames to be under it: stopped early ({detail} so far)",
            fix,
        )
    if p95 > brain_timeout_s:
        return Check(
            "answer time",
            "fail",
            detail + f" (lock-step episodes end after {brain_timeout_s:g} s)",
            fix,
        )
    if p50 > REALTIME_BUDGET_S:
        return Check(
            "answer time", "warn", detail + " (lock-step is fine; real-time runs at 20 Hz will skip frames)", ""
        )
    return Check("answer time", "pass", detail)


def _check_determinism(
    brain: Any,
    make_new: Callable[[], Any],
    frames: list[Frame],
    first: list[tuple[float, float]],
    *,
    say: Callable[..., None],
) -> Check:
    fix = "seed every random generator from reset(seed=...) and clear everything the brain remembers in reset"
    say("determinism: 3 more runs over the frames", now=True)
    try:
        _drive(brain, frames[::-1], seed=2, say=say, what="determinism, run 1 of 3 (other frames)")
        again, _ = _drive(brain, frames, seed=1, say=say, what="determinism, run 2 of 3 (seed 1 again)")
        fresh, _ = _drive(make_new(), frames, seed=1, say=say, what="determinism, run 3 of 3 (a new brain)")
    except Exception as error:
        detail = f"a second run raised {type(error).__name__}: {error}"
        return Check("determinism", "fail", detail, fix, wall=_wall(error))
    if again != first:
        return Check(
            "determinism",
            "fail",
            f"after other frames, reset(seed=1) gave other actions from frame {_first_difference(first, again)}",
            fix,
        )
    if fresh != first:
        return Check(
            "determinism",
            "fail",
            f"a new brain with seed 1 gave other actions from frame {_first_difference(first, fresh)}",
            fix,
        )
    return Check("determinism", "pass", "same seed, same frames: same actions (after other frames, and fresh)")


def _first_difference(a: list, b: list) -> int:
    return next((i for i, (x, y) in enumerate(zip(a, b)) if x != y), min(len(a), len(b)))


def _check_memory(brain: Any, frames: list[Frame], *, steps: int, say: Callable[..., None]) -> Check:
    """Python/NumPy heap (tracemalloc) and resident memory growth between step 30 and step ``steps``."""
    long_run = [frames[i % len(frames)] for i in range(steps)]
    warm = min(30, steps // 2)
    say(f"memory: {warm} warm-up frames, then {steps}", now=True)
    tracemalloc.start()
    try:
        _drive(brain, long_run[:warm], seed=3, say=say, what="memory, warm-up")
        heap_before, rss_before = tracemalloc.get_traced_memory()[0], _rss_bytes()
        brain.reset(seed=3)  # _drive resets; run the rest without a reset in between, as one long episode does
        for seq, frame in enumerate(long_run):
            truth = frame.truth if getattr(brain, "needs_ground_truth", False) else None
            brain.act(Observation(image_rgb=frame.image_rgb, stamp_ns=seq * STEP_NS, seq=seq, ground_truth=truth))
            say(f"memory: frame {seq + 1}/{steps}")
        heap_growth = tracemalloc.get_traced_memory()[0] - heap_before
        rss_growth = _rss_bytes() - rss_before
    except Exception as error:
        return Check(
            "memory",
            "fail",
            f"act raised {type(error).__name__} on frame {steps} frames long: {error}",
            "act must keep answering through a long episode",
            wall=_wall(error),
        )
    finally:
        tracemalloc.stop()
    growth = max(heap_growth, rss_growth)
    detail = f"{steps} frames: heap {heap_growth / 2**20:+.1f} MiB, resident {rss_growth / 2**20:+.1f} MiB"
    if growth > MEMORY_GROWTH_LIMIT_BYTES:
        return Check(
            "memory",
            "fail",
            detail,
            "keep a bounded history (collections.deque(maxlen=...)), not every "
            "frame; release what the previous frames needed",
        )
    return Check("memory", "pass", detail)


def _rss_bytes() -> int:
    try:
        return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:  # not Linux: the heap figure alone decides
        return 0
