"""drivebench/LaneFollow-v0 over the real stack: Gymnasium's checker, determinism, the same trajectory as the same
commands through ``drivebench run``, bad input, clean close, attaching, vector envs, a training smoke."""

from __future__ import annotations

import functools
import json
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
from needs import require
from support.processes import environment_of

gym = require("gymnasium")
import drivebench  # noqa: E402,F401 - registers the environment
from drivebench.rl.env import LaneFollowEnv  # noqa: E402

pytestmark = pytest.mark.integration
ENV_ID = "drivebench/LaneFollow-v0"
SMALL = dict(camera=(64, 48), max_episode_s=20.0)  # TinyRenderer at 64 x 48: hundreds of steps a second


def rollout(env, *, seed: int, actions: np.ndarray):
    """Observations and rewards of one episode from reset(seed) driven by ``actions`` (stops at the end)."""
    obs, _ = env.reset(seed=seed)
    observations, rewards = [obs], []
    for action in actions:
        obs, reward, terminated, truncated, _ = env.step(action)
        observations.append(obs)
        rewards.append(reward)
        if terminated or truncated:
            break
    return observations, rewards


def test_gymnasium_env_checker_passes_on_the_environment_as_made():
    """The registered default, made with no argument, passes Gymnasium's own checker (the same seed and actions
    give the same info: live metrics, which arrive on wall-clock time, are off unless asked for)."""
    from gymnasium.utils.env_checker import check_env

    env = gym.make(ENV_ID)
    try:
        check_env(env.unwrapped)
    finally:
        env.close()
    rendering = gym.make(ENV_ID, render_mode="rgb_array", **SMALL)
    try:
        check_env(rendering.unwrapped)
    finally:
        rendering.close()


@pytest.mark.slow
def test_same_seed_and_actions_give_the_same_observations_and_rewards_bit_for_bit():
    actions = np.random.default_rng(7).uniform([0.0, -0.4], [0.6, 0.4], size=(80, 2)).astype(np.float32)
    kwargs = dict(noise="gaussian=20", variation=["", "line=white"], **SMALL)  # the noise is seeded by reset's seed
    first, second = gym.make(ENV_ID, **kwargs), gym.make(ENV_ID, **kwargs)  # two stacks
    try:
        obs_a, rewards_a = rollout(first, seed=3, actions=actions)
        obs_b, rewards_b = rollout(second, seed=3, actions=actions)
        obs_c, rewards_c = rollout(first, seed=3, actions=actions)  # the same stack, reused
        obs_d, _ = rollout(first, seed=4, actions=actions[:5])
    finally:
        first.close()
        second.close()
    assert len(obs_a) > 20 and len(obs_a) == len(obs_b) == len(obs_c)
    assert all(np.array_equal(a, b) and np.array_equal(a, c) for a, b, c in zip(obs_a, obs_b, obs_c))
    assert rewards_a == rewards_b == rewards_c and any(r != 0 for r in rewards_a)
    assert not np.array_equal(obs_a[0], obs_d[0])  # another seed: other noise


@pytest.mark.parametrize("family", ["random", "grandprix"])
def test_a_generated_circuit_is_drawn_from_the_seed(family):
    env = gym.make(ENV_ID, circuit=["simple", f"{family}:*"], **SMALL)
    try:
        names = [env.reset(seed=seed, options={"circuit": f"{family}:*"})[1]["circuit"] for seed in (1, 2, 1)]
        _, info = env.reset(seed=1)
        with pytest.raises(ValueError, match="not one of"):
            env.reset(options={"circuit": "montmelo"})
    finally:
        env.close()
    assert names[0] == names[2] != names[1] and all(name.startswith(f"{family}:") for name in names)
    assert info["circuit"] in ("simple", names[0])


def test_an_episode_starts_where_reset_says_or_where_the_seed_draws_it():
    from circuits import load_circuit

    circuit = load_circuit("simple")
    env = gym.make(ENV_ID, start="random", **SMALL).unwrapped
    try:
        _, chosen = env.reset(seed=5, options={"start_m": 300.0})
        _, reward, *_ = env.step(np.array([0.5, 0.0], np.float32))
        starts = [env.reset(seed=seed)[1] for seed in (5, 6, 5)]
        with pytest.raises(ValueError) as too_far:
            env.reset(options={"start_m": 500})
        with pytest.raises(ValueError, match=r"^reset options: start_m must be a number of metres, got '40'$"):
            env.reset(options={"start_m": "40"})
        _, _, terminated, truncated, info = env.step(np.array([0.5, 0.0], np.float32))
        assert info["seq"] == 1 and not terminated and not truncated  # the episode went on where it was
    finally:
        env.close()
    assert chosen["start_m"] == 300.0 and chosen["progress_m"] == 0.0
    assert (chosen["x_m"], chosen["y_m"], chosen["yaw_rad"]) == circuit.centreline.pose_at(300.0)
    assert 0.0 < reward < 1.0  # a step's progress from 300 m, not the start line's 300 m behind
    assert starts[0]["start_m"] == starts[2]["start_m"] != starts[1]["start_m"]  # the seed draws the start
    assert all(0.0 <= info["start_m"] < circuit.length_m for info in starts)
    assert all((i["x_m"], i["y_m"]) == circuit.centreline.pose_at(i["start_m"])[:2] for i in starts)
    assert str(too_far.value) == (
        "reset options: start_m must be >= 0 and below 442.836 m, the length of circuit 'simple', got 500"
    )


def test_a_scripted_sequence_drives_as_the_same_commands_through_drivebench_run(tmp_path):
    """The environment's trajectory equals that of ``drivebench run`` with a brain that answers the same commands."""
    from brains.lane_policy.features import scaled

    speed_range, yaw_range = (0.0, 4.0), (-0.25, 0.25)
    action = np.array([0.5, 0.5], np.float32)  # -> 3.0 m/s, 0.125 rad/s exactly
    speed_mps, yaw_rate_radps = scaled(action[0], *speed_range), scaled(action[1], *yaw_range)
    env = gym.make(ENV_ID, speed_range_mps=speed_range, yaw_rate_range_radps=yaw_range, **SMALL)
    try:
        env.reset(seed=0)
        steps, info = 0, {}
        while not info.get("end_reason"):
            _, _, _, _, info = env.step(action)
            steps += 1
    finally:
        env.close()
    # The constant brain sends the same command every frame; the run's renderer default is the env's (pybullet).
    argv = ["run", "--brain", "constant", "--brain-option", f"speed_mps={speed_mps}"]
    argv += ["--brain-option", f"yaw_rate_radps={yaw_rate_radps}", "--camera", "64x48", "--max-sim-seconds", "20"]
    argv += ["--json", "--runs-dir", str(tmp_path)]
    result = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *argv], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    score = json.loads(result.stdout.strip().splitlines()[-1])
    ours, theirs = info["score"], score["metrics"]
    assert info["end_reason"] == score["reason"] == "crash"
    assert steps == ours["steps"] == theirs["steps"]
    for name in ("progress_m", "completed_distance_m", "cross_track_mean_m", "cross_track_max_m", "sim_time_s"):
        assert ours[name] == theirs[name], name
    assert info["progress_m"] == pytest.approx(theirs["progress_m"], abs=1e-9)


def test_bad_input_is_one_clear_error_and_the_env_goes_on():
    for kwargs, words in [
        (dict(circuit="nowhere"), "circuit='nowhere'"),
        (dict(variation="line=purple"), "variation='line=purple'"),
        (dict(camera="12x"), "camera must be"),
        (dict(observation="pixels"), "observation must be"),
        (dict(speed_range_mps=(3, 1)), "speed_range_mps"),
        (dict(noise="sparkles=1"), "noise="),
        (dict(start="anywhere"), "start must be one of line, random, got 'anywhere'"),
        (dict(variation=["", "start_m=443"]), "variation='start_m=443': start_m must be >= 0 and below 442.836 m"),
        (
            dict(start="random", variation=["", "start_m=100"]),
            "start='random' draws each episode's start, and variation='start_m=100' sets one: give one of them",
        ),
        (dict(render_threads=0), "render_threads must be an integer >= 1, got 0"),
        (dict(render_threads=2, router="tcp/127.0.0.1:7447"), "render_threads=2 needs the environment's own stack"),
    ]:
        with pytest.raises(ValueError, match=words.replace("(", r"\(").replace("[", r"\[")):
            gym.make(ENV_ID, **kwargs)
    port = _closed_port()
    with pytest.raises(ConnectionError, match=f"router='tcp/127.0.0.1:{port}'"):
        gym.make(ENV_ID, router=f"tcp/127.0.0.1:{port}")
    env = gym.make(ENV_ID, **SMALL).unwrapped  # unwrapped: Gymnasium's checker wrapper would assert first
    try:
        with pytest.raises(RuntimeError, match="reset"):
            env.step(np.zeros(2, np.float32))
        env.reset(seed=0)
        for action, words in [
            ([0.0, float("nan")], "finite"),
            ([0.0, 1.5], r"in \[-1, 1\]"),
            ([0.0, 0.0, 0.0], "shape"),
            ("fast", "2 numbers"),
        ]:
            with pytest.raises(ValueError, match=words):
                env.step(action)
        with pytest.raises(ValueError, match="unknown"):
            env.reset(options={"weather": "rain"})
        _, reward, terminated, truncated, info = env.step(np.array([0.5, 0.0], np.float32))
        assert info["seq"] == 1 and not terminated and not truncated  # the episode went on where it was
    finally:
        env.close()


def _closed_port() -> int:
    from orchestrator.stack.launcher import free_loopback_port

    return free_loopback_port()


def test_close_twice_is_safe_and_nothing_outlives_the_env():
    env = gym.make(ENV_ID, **SMALL)
    env.reset(seed=0)
    env.step(np.zeros(2, np.float32))
    stack = env.unwrapped._parts["stack"]
    run_dir = Path(env.unwrapped._parts["run_dir"])
    processes = [child.process for child in stack.children]
    assert len(processes) == 3 and all(p.poll() is None for p in processes)  # simulator, noise injector, scorer
    env.close()
    env.close()
    assert all(p.poll() is not None for p in processes)
    assert not run_dir.exists()
    with pytest.raises(RuntimeError, match="closed"):
        env.reset()


def test_the_environments_simulator_renders_on_the_threads_it_is_given(monkeypatch):
    monkeypatch.delenv("LP_NUM_THREADS", raising=False)
    env = gym.make(ENV_ID, render_threads=2, **SMALL)  # any renderer: the variable is set, gl reads it
    try:
        env.reset(seed=0)
        stack = env.unwrapped._parts["stack"]
        (simulator,) = (child for child in stack.children if child.role == "simulator")
        assert environment_of(simulator.process.pid)["LP_NUM_THREADS"] == "2"
    finally:
        env.close()


NEVER_CLOSED = """
import sys
import numpy as np
import gymnasium as gym
import drivebench
env = gym.make("drivebench/LaneFollow-v0", camera=(64, 48), max_episode_s=20.0)
env.reset(seed=0)
env.step(np.zeros(2, np.float32))
print(" ".join(str(child.process.pid) for child in env.unwrapped._parts["stack"].children), flush=True)
if sys.argv[1] == "raise":
    raise RuntimeError("the script failed")
"""


def _gone(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/status").read_text().split("State:")[1].split()[0] == "Z"  # exited, not reaped
    except (FileNotFoundError, IndexError):
        return True


@pytest.mark.parametrize("ending", ["end", "raise"])
def test_a_script_that_never_closes_its_env_exits_and_leaves_no_process(ending):
    # Zenoh's callback threads kept such a script waiting for ever at exit (until the env's stack was closed).
    child = subprocess.run([sys.executable, "-c", NEVER_CLOSED, ending], capture_output=True, text=True, timeout=60)
    assert child.returncode == (0 if ending == "end" else 1), child.stderr
    assert ending == "end" or "RuntimeError: the script failed" in child.stderr
    pids = [int(pid) for pid in child.stdout.split()]
    assert len(pids) == 3  # simulator, noise injector, scorer
    deadline = time.monotonic() + 10.0
    while not all(_gone(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert all(_gone(pid) for pid in pids)


def test_router_attaches_to_a_running_stack_and_leaves_it_running(tmp_path):
    from drivebench.rl.stack import open_stack

    run_id = f"t-{uuid.uuid4().hex[:6]}"
    stack = open_stack(router=None, run_id=run_id, run_dir=tmp_path, startup_timeout_s=60)
    try:
        env = gym.make(ENV_ID, router=stack.endpoint, run_id=run_id, **SMALL)
        _, info = env.reset(seed=0)
        for _ in range(5):
            _, reward, *_ = env.step(np.array([0.5, 0.0], np.float32))
        assert info["seq"] == 0 and reward > 0
        env.close()
        assert stack.dead_child_reason() is None  # attached: nothing of the stack was stopped
        with pytest.raises(ConnectionError, match="run 'nobody' on .*: not alive after 2 s: .*simulator"):
            gym.make(ENV_ID, router=stack.endpoint, run_id="nobody", startup_timeout_s=2).reset()
    finally:
        stack.close()


@pytest.mark.slow
def test_async_vector_env_and_sb3_subproc_vec_env_with_two_envs():
    from gymnasium.vector import AsyncVectorEnv

    make = functools.partial(LaneFollowEnv, observation="features", **SMALL)
    vector = AsyncVectorEnv([make, make], context="spawn")
    try:
        obs, infos = vector.reset(seed=[1, 2])
        assert obs.shape == (2, 10) and len(set(infos["run_id"])) == 2  # each its own stack and run
        for _ in range(30):
            obs, rewards, *_ = vector.step(np.tile(np.array([[0.4, 0.0]], np.float32), (2, 1)))
        assert obs.shape == (2, 10) and rewards.shape == (2,) and np.all(rewards > 0)
    finally:
        vector.close()
    require("stable_baselines3")
    from stable_baselines3.common.vec_env import SubprocVecEnv

    sb3 = SubprocVecEnv([make, make], start_method="spawn")
    try:
        obs = sb3.reset()
        for _ in range(30):
            obs, rewards, dones, infos = sb3.step(np.tile(np.array([[0.4, 0.0]], np.float32), (2, 1)))
        assert obs.shape == (2, 10) and np.all(rewards > 0) and infos[0]["run_id"] != infos[1]["run_id"]
    finally:
        sb3.close()


@pytest.mark.slow
def test_a_few_hundred_training_steps_export_a_policy_the_brain_serves(tmp_path):
    require("stable_baselines3")
    torch = require("torch")
    from stable_baselines3 import SAC

    from brains.base import Observation
    from brains.lane_policy.brain import LanePolicyBrain
    from brains.lane_policy.features import line_features
    from drivebench.rl.policy import export_sb3

    torch.set_num_threads(1)
    ranges = dict(speed_range_mps=(2.0, 8.0), yaw_rate_range_radps=(-2.0, 2.0))
    env = gym.make(ENV_ID, observation="features", render_mode="rgb_array", **ranges, **SMALL)
    try:
        model = SAC("MlpPolicy", env, policy_kwargs=dict(net_arch=[16, 16]), learning_starts=100, seed=0)
        model.learn(total_timesteps=300)
        image = env.render()  # the camera frame of the last step
    finally:
        env.close()
    assert model.num_timesteps == 300
    path = export_sb3(model, tmp_path / "policy.npz", **ranges)
    brain = LanePolicyBrain(weights=str(path))
    brain.reset(seed=0)
    action = brain.act(Observation(image_rgb=image, stamp_ns=0, seq=0))
    expected, _ = model.predict(line_features(image, previous_action=np.zeros(2)), deterministic=True)
    assert action.speed_mps == pytest.approx(2.0 + (expected[0] + 1) * 3.0, abs=1e-4)
    assert action.yaw_rate_radps == pytest.approx(-2.0 + (expected[1] + 1) * 2.0, abs=1e-4)
