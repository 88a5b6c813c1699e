"""Stable Foxglove topic names: what recordings and the live view call each channel, the same in every run.

Bus keys carry the run id (``drivebench/run/<run>/sim/camera``) so that runs never cross-talk on the bus. Viewers
need the opposite: one layout that shows any run, two runs opened with one set of panels. So recordings and the live
view name channels by what they hold, not by run:

=========================  =================================  ================================================
topic                      bus key (``<p>`` = run prefix)     schema
=========================  =================================  ================================================
``/camera/truth``          ``<p>/sim/camera``                 ``foxglove.RawImage`` / ``CompressedImage``
``/camera/brain``          ``<p>/noise/camera``               same (the perturbed frames brains see)
``/car/state``             ``<p>/sim/pose``                   ``drivebench.Pose.v1`` (speed, yaw rate, latency)
``/brain/<name>/cmd``      ``<p>/brain/<name>/cmd``           ``drivebench.Command.v1``
``/metrics/live``          ``<p>/scorer/live``                ``drivebench.LiveMetrics.v1``
``/episode/score``         ``<p>/scorer/score``               ``drivebench.EpisodeScore.v1``
``/episode/events``        ``<p>/sim/events``                 ``drivebench.EpisodeEvent.v1``
``/car/pose``              view of ``<p>/sim/pose``           ``foxglove.PoseInFrame``
``/tf``                    view of ``<p>/sim/pose``           ``foxglove.FrameTransform`` (``world`` -> ``car``)
``/circuit``               view of the START event            ``foxglove.SceneUpdate``
``/episode/log``           view of ``<p>/sim/events``         ``foxglove.Log`` (one line per event)
=========================  =================================  ================================================

The run id and episode stay where they belong: in every bus message's header (JSON ``header.run_id``, the images'
``drivebench_run_id`` field), in channel metadata (``drivebench.key``, ``drivebench.run_id``) and in file metadata
(``drivebench.run``). Readers map a channel back to its bus key from ``drivebench.key``, never from its topic.

Files recorded before stable topics used the bus key as topic and ``<p>/view/<name>`` for views;
:func:`stable_topic` maps those too (the legacy mapping), so old files still read, replay and merge.
"""

from __future__ import annotations

import re

from protocol import keys

RUN_ID_METADATA = "drivebench.run_id"
VIEW_METADATA = "drivebench.view"
NAMESPACE_METADATA = "drivebench.namespace"  # the run's namespace in a merged file (recorder.merge)

CAMERA_TRUTH = "/camera/truth"
CAMERA_BRAIN = "/camera/brain"
CAR_STATE = "/car/state"
CAR_POSE = "/car/pose"
TF = "/tf"
CIRCUIT = "/circuit"
EPISODE_EVENTS = "/episode/events"
EPISODE_LOG = "/episode/log"
EPISODE_SCORE = "/episode/score"
METRICS_LIVE = "/metrics/live"
COMMAND_PATTERN = "/brain/{brain}/cmd"

# Bus key (after the run prefix) -> topic.
_BUS_TOPICS = {
    "sim/camera": CAMERA_TRUTH,
    "noise/camera": CAMERA_BRAIN,
    "sim/pose": CAR_STATE,
    "sim/events": EPISODE_EVENTS,
    "scorer/live": METRICS_LIVE,
    "scorer/score": EPISODE_SCORE,
}
# View name -> topic. The names are those of old files' ``<p>/view/<name>`` topics (the legacy mapping).
VIEW_TOPICS = {"car_pose": CAR_POSE, "world_from_car": TF, "track": CIRCUIT, "episode_log": EPISODE_LOG}
_COMMAND = re.compile(r"brain/([\w.-]+)/cmd")  # brain names as keys.check_name takes them
_STABLE_COMMAND = re.compile(r"/brain/([\w.-]+)/cmd")


def command_topic(brain: str) -> str:
    return COMMAND_PATTERN.format(brain=keys.check_name(brain, what="brain name"))


def topic_of_key(key: str) -> str:
    """The stable topic of the channel that holds run key ``key`` (a ValueError for a key outside every run).

    A key the table does not know (a message type added later) keeps its path without the run prefix
    (``<p>/x/y`` -> ``/x/y``): still the same in every run, and never a crash in the recorder."""
    keys.run_of_key(key)  # checks that it is a run key
    rest = key.split("/", 3)[3]
    if rest in _BUS_TOPICS:
        return _BUS_TOPICS[rest]
    if (match := _COMMAND.fullmatch(rest)) is not None:
        return command_topic(match.group(1))
    return f"/{rest}"


def view_topic(name: str) -> str:
    """The stable topic of a view (``protocol.mapping.views``): ``car_pose``, ``world_from_car``, ``track``,
    ``episode_log``."""
    try:
        return VIEW_TOPICS[name]
    except KeyError:
        raise ValueError(f"no view named {name!r}") from None


def stable_topic(topic: str) -> str:
    """The stable topic of any recorded topic: itself when stable already, else the one an old file's run-id topic
    (``drivebench/run/<run>/sim/camera``, ``drivebench/run/<run>/view/track``) stands for."""
    if topic.startswith("/"):
        return topic
    parts = topic.split("/", 3)
    if len(parts) == 4 and parts[:2] == [keys.ROOT, "run"]:
        view = parts[3].removeprefix("view/")
        if view != parts[3] and view in VIEW_TOPICS:
            return VIEW_TOPICS[view]
        return topic_of_key(topic)
    raise ValueError(f"not a drivebench topic: {topic!r}")


def is_stable_topic(topic: str, *, brains: tuple[str, ...] | None = None) -> bool:
    """True for a topic of :data:`TOPICS` or a brain's command topic (of one of ``brains`` when given)."""
    if topic in TOPICS:
        return True
    match = _STABLE_COMMAND.fullmatch(topic)
    return match is not None and (brains is None or match.group(1) in brains)


def run_topics(*, brains: tuple[str, ...] = (), perturbed: bool = True, score: bool = True) -> set[str]:
    """Every topic one run publishes: its brains' commands, the perturbed camera when a noise injector runs, the
    score once an episode ended."""
    topics = set(TOPICS) | {command_topic(brain) for brain in brains}
    if not perturbed:
        topics.discard(CAMERA_BRAIN)
    if not score:
        topics.discard(EPISODE_SCORE)
    return topics


# Every topic but the brains' commands (one per brain: COMMAND_PATTERN).
TOPICS: frozenset[str] = frozenset(_BUS_TOPICS.values()) | frozenset(VIEW_TOPICS.values())


# -- comparing runs: one namespace per run (``recorder.merge``) --------------------------------------------------------

# Namespaces ``drivebench recorder merge`` gives its inputs in order, unless named: fixed, so that one shipped layout
# (docs/foxglove/drivebench-compare-layout.json) shows any merged pair.
DEFAULT_NAMESPACES = ("runA", "runB", "runC", "runD", "runE", "runF", "runG", "runH")


def namespaced(topic: str, namespace: str) -> str:
    """``/camera/truth`` of run namespace ``runA`` -> ``/runA/camera/truth``."""
    return f"/{keys.check_name(namespace, what='namespace')}{stable_topic(topic)}"


def namespaced_frame(frame_id: str, namespace: str, *, shared: frozenset[str] = frozenset({"world"})) -> str:
    """A coordinate frame of one run in a merged file: ``car`` -> ``runA/car``; the ``world`` frame is shared, so both
    cars and circuits are drawn in one 3D view."""
    return frame_id if frame_id in shared or not frame_id else f"{namespace}/{frame_id}"
