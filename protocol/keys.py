"""Every Zenoh key expression of the project is built here; nowhere else writes key strings.

Layout (``<p>`` = ``drivebench/run/<run_id>``, so ``<p>/**`` is one run and runs never cross-talk):

    <p>/sim/camera               CameraFrame, ground truth (what the simulator rendered)
    <p>/noise/camera             CameraFrame, perturbed (what brains see when a noise injector runs)
    <p>/sim/pose                 Pose, ground truth
    <p>/sim/events               EpisodeEvent
    <p>/sim/brain_events         BrainEvent: START and END as brains see them (no conditions)
    <p>/sim/control              queryable: ControlRequest -> ControlReply (start, stop, switch, status)
    <p>/sim/status               queryable: anything -> ControlReply of "status" (read-only: any process may ask)
    <p>/brain/<brain>/cmd        Command of one brain (the simulator applies only the active one)
    <p>/brain/<brain>/control    queryable of one brain host: ControlRequest -> ControlReply (status, stop)
    <p>/scorer/live              LiveMetrics
    <p>/scorer/score             EpisodeScore

Liveliness tokens live under ``drivebench/alive/<run_id>/<role>/<name>``.
"""

from __future__ import annotations

import re

ROOT = "drivebench"
_NAME = re.compile(r"[\w.-]+")  # \w: Unicode letters and digits too (a label "élève"): Zenoh keys are UTF-8


def check_name(name: str, *, what: str) -> str:
    """Run ids, brain names and roles become key chunks: no '/', '*', '$', '?', '#' or spaces."""
    if not _NAME.fullmatch(name):  # fullmatch: "$" would let a trailing newline through
        raise ValueError(f"{what} {name!r} may only contain letters, digits, '_', '.', '-'")
    return name


def run_prefix(run_id: str) -> str:
    return f"{ROOT}/run/{check_name(run_id, what='run id')}"


def run_all(run_id: str) -> str:
    """Everything published in one run (what the recorder subscribes to)."""
    return f"{run_prefix(run_id)}/**"


def run_of_key(key: str) -> str:
    """The run id inside a run-scoped key."""
    parts = key.split("/")
    if len(parts) < 4 or parts[0] != ROOT or parts[1] != "run":
        raise ValueError(f"not a run key: {key!r}")
    return parts[2]


def with_run_id(key: str, run_id: str) -> str:
    """The same key in another run (replay under a new run id)."""
    run_of_key(key)  # checks that it is one
    return f"{run_prefix(run_id)}/{key.split('/', 3)[3]}"


def view(run_id: str, name: str) -> str:
    """The viewer topics of recordings made before stable topics (format 1); never published. Today's recordings
    name them ``/car/pose``, ``/tf``, ``/circuit`` (``protocol.mapping.topics``, which maps these old names)."""
    return f"{run_prefix(run_id)}/view/{check_name(name, what='view')}"


def camera_raw(run_id: str) -> str:
    return f"{run_prefix(run_id)}/sim/camera"


def camera_perturbed(run_id: str) -> str:
    return f"{run_prefix(run_id)}/noise/camera"


def pose(run_id: str) -> str:
    return f"{run_prefix(run_id)}/sim/pose"


def events(run_id: str) -> str:
    return f"{run_prefix(run_id)}/sim/events"


def brain_events(run_id: str) -> str:
    """The episode events a brain host reads (``BrainEvent``): its seed and mode, none of the episode's conditions.
    Apart from :func:`events` so that access control can give an untrusted brain this key and not that one."""
    return f"{run_prefix(run_id)}/sim/brain_events"


def sim_control(run_id: str) -> str:
    return f"{run_prefix(run_id)}/sim/control"


def sim_status(run_id: str) -> str:
    """The simulator's read-only status queryable, apart from ``sim_control`` so that access control can let every
    process read the status while only the orchestrator may start, stop or switch."""
    return f"{run_prefix(run_id)}/sim/status"


def recorder_control(run_id: str) -> str:
    """The recorder's control queryable (``status``; ``open`` a file, ``close`` it: one file per episode of a warm
    matrix stack)."""
    return f"{run_prefix(run_id)}/recorder/control"


def command(run_id: str, brain: str) -> str:
    return f"{run_prefix(run_id)}/brain/{check_name(brain, what='brain name')}/cmd"


def brain_control(run_id: str, brain: str) -> str:
    """Control queryable of one brain host (``status``, ``stop``)."""
    return f"{run_prefix(run_id)}/brain/{check_name(brain, what='brain name')}/control"


def commands_all(run_id: str) -> str:
    return f"{run_prefix(run_id)}/brain/*/cmd"


def brain_of_command_key(key: str) -> str:
    """The brain name inside a key made by :func:`command`."""
    parts = key.split("/")
    return parts[-2]


def live_metrics(run_id: str) -> str:
    return f"{run_prefix(run_id)}/scorer/live"


def score(run_id: str) -> str:
    return f"{run_prefix(run_id)}/scorer/score"


def alive(run_id: str, role: str, name: str) -> str:
    """Liveliness token of one process of one run."""
    run, role_name = check_name(run_id, what="run id"), check_name(role, what="role")
    return f"{ROOT}/alive/{run}/{role_name}/{check_name(name, what='name')}"


def alive_role(run_id: str, role: str) -> str:
    """Every liveliness token of one role in one run (e.g. its simulators)."""
    return f"{ROOT}/alive/{check_name(run_id, what='run id')}/{check_name(role, what='role')}/*"


def alive_all(run_id: str) -> str:
    return f"{ROOT}/alive/{check_name(run_id, what='run id')}/**"


def alive_everywhere() -> str:
    """Every liveliness token of every run (to find which runs are alive on a router)."""
    return f"{ROOT}/alive/**"


def parse_alive(key: str) -> tuple[str, str, str]:
    """(run_id, role, name) of a key made by :func:`alive`."""
    parts = key.split("/")
    if len(parts) != 5 or parts[0] != ROOT or parts[1] != "alive":
        raise ValueError(f"not a liveliness key: {key!r}")
    return parts[2], parts[3], parts[4]


CLAIM_ROLE = "claim"


def name_claim(run_id: str, name: str, claimant: str) -> str:
    """Liveliness token by which ``claimant`` (a unique id) reserves brain name ``name`` while it starts that brain
    (a live swap), so that two swaps at once never start two brains of one name."""
    return alive(run_id, CLAIM_ROLE, f"{check_name(name, what='brain name')}.{check_name(claimant, what='claimant')}")


def name_claims(run_id: str) -> str:
    """Every name claim of one run."""
    return alive_role(run_id, CLAIM_ROLE)


def parse_name_claim(key: str) -> tuple[str, str]:
    """(brain name, claimant) of a key made by :func:`name_claim`; the claimant holds no '.', the name may."""
    name, _, claimant = parse_alive(key)[2].rpartition(".")
    return name, claimant
