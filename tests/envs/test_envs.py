"""The Gymnasium environments (safeil_sumo/envs, docs/gymnasium.md), on real libsumo runs.

Every registered id passes Gymnasium's env checker; a seed gives the same episode; the shipped
``safeil`` driven through the env reproduces ``python -m safeil_sumo.run``'s results; the native
vector env gives the trajectories of N single envs (autoreset included); bad input fails
clearly; closing or killing ends SUMO; PPO trains on the vector env (when SB3 is installed).
"""

from __future__ import annotations

import contextlib
import itertools
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.utils.passive_env_checker import env_render_passive_checker

from safeil_sumo import api, envs
from safeil_sumo.data.sources import DEFAULT_DATA_DIR
from safeil_sumo.planners import registry as planner_registry

pytest.importorskip("libsumo")
psutil = pytest.importorskip("psutil")

CURVED = "safeil_sumo/Curved500-v0"
HAS_DATA = (DEFAULT_DATA_DIR / "ngsim_i80").is_dir()
REPO = Path(__file__).resolve().parents[2]


def _plan(policy, features: np.ndarray) -> np.ndarray:
    return np.asarray(policy.plan(np.atleast_2d(features)), float).reshape(-1, 6)


@pytest.mark.sumo
@pytest.mark.parametrize("env_id", list(envs.IDS))
def test_check_env_passes_for_every_id(env_id):
    if env_id in envs.DATA_IDS and not HAS_DATA:
        if os.environ.get("CI"):
            pytest.fail(f"{env_id} needs the shared data ({DEFAULT_DATA_DIR})")
        pytest.skip(f"{env_id} needs the shared data ({DEFAULT_DATA_DIR})")
    env = gym.make(env_id, max_time_s=3.0)
    try:
        # check_env's render check makes an env of every render mode: "human" needs a display
        # (sumo-gui: tests/sim/test_gui.py); rgb_array is checked here
        check_env(env.unwrapped, skip_render_check=True)
        if env_id == CURVED:
            drawn = gym.make(env_id, max_time_s=3.0, render_mode="rgb_array")
            try:
                drawn.reset(seed=0)
                env_render_passive_checker(drawn.unwrapped)
            finally:
                drawn.close()
        obs, info = env.reset(seed=1)
        assert env.observation_space.contains(obs)
        assert {"ttc", "gap", "lateral_offset", "lane_departure", "ttc_flag",
                "collision"} <= set(info)
    finally:
        env.close()


def _episode(env, seed, actions):
    obs, _ = env.reset(seed=seed)
    out = [obs]
    rewards = []
    for a in actions:
        obs, r, te, tr, _ = env.step(a)
        out.append(obs)
        rewards.append(r)
        if te or tr:
            break
    return np.array(out), np.array(rewards), env.unwrapped.rollout().log


@pytest.mark.sumo
def test_reset_with_a_seed_gives_the_same_episode():
    """Twice in one process: the same index, observations, rewards and SUMO state (the leader
    read back from SUMO, in the log); another seed another episode."""
    env = gym.make(CURVED, max_time_s=2.0, lane_noise_c0_m=0.05, radar_noise_m=0.5)
    rng = np.random.default_rng(0)
    actions = [np.array([30.0, 0.0, 60.0, 0.0, 90.0, 0.0]) + rng.normal(0, 0.5, 6)
               for _ in range(25)]
    try:
        o1, r1, log1 = _episode(env, 7, actions)
        i1 = env.unwrapped.index
        o2, r2, log2 = _episode(env, 7, actions)
        assert env.unwrapped.index == i1
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_array_equal(r1, r2)
        np.testing.assert_array_equal(log1[["leader_x", "leader_y", "x", "y"]].to_numpy(),
                                      log2[["leader_x", "leader_y", "x", "y"]].to_numpy())
        _episode(env, 8, actions[:1])
        assert env.unwrapped.index != i1
    finally:
        env.close()


@pytest.mark.sumo
def test_brake_guard_option():
    """The loop's brake guard is on by default under plan actions and ``brake_guard=False``
    turns it off: a plan that ignores a braking leader is braked by the guard only."""
    from safeil_sumo.planners.analytic import AnalyticPlanner

    logs = {}
    for guard in (True, False):
        env = gym.make("safeil_sumo/Braking-v0", brake_guard=guard, max_time_s=12.0)
        try:
            assert (env.unwrapped.loop_config.brake_guard is not None) == guard
            _, info = env.reset(options={"index": 0})
            done = False
            while not done:  # the analytic plan's lane keeping at a held speed: blind
                plan = _plan(AnalyticPlanner(), info["features"]).reshape(3, 2)
                plan[:, 0] = info["features"][6] * 5.0 * np.arange(1, 4) / 3.0
                _, _, te, tr, info = env.step(plan.reshape(-1))
                done = te or tr
            logs[guard] = env.unwrapped.rollout().log
        finally:
            env.close()
    assert (logs[True]["guard_decel"] > 0).any()
    assert logs[False]["guard_decel"].isna().all()
    assert logs[True]["gap"].min() > logs[False]["gap"].min()


@pytest.mark.sumo
def test_safeil_through_the_env_reproduces_run():
    """The shipped safeil planning from info["features"] gives run's flags and path."""
    policy = planner_registry.load("safeil")
    ref = api.run("curved500", policy, scenarios=2).summary
    env = gym.make(CURVED)
    try:
        for i in range(2):
            _, info = env.reset(options={"index": i})
            done = False
            while not done:
                _, _, te, tr, info = env.step(_plan(policy, info["features"])[0])
                done = te or tr
            got = env.unwrapped.rollout().summary
            want = ref.iloc[i]
            for key in ("scenario", "end_reason", "flag", "completed", "path_completed",
                        "steps"):
                assert got[key] == want[key], key
            # the stepper against run_scenario: within tests/sim/test_batch.py's tolerances
            assert got["min_ttc_s"] == pytest.approx(want["min_ttc_s"], rel=1e-6)
            assert got["min_gap_m"] == pytest.approx(want["min_gap_m"], abs=1e-6)
            assert info["end_reason"] == "completed" and info["path_fraction"] == 1.0
    finally:
        env.close()


@pytest.mark.sumo
def test_a_coarser_physics_step_drives_the_same_episodes():
    """step_s=0.1 (one physics step per 10 Hz decision, the env's speed lever): the shipped
    safeil completes the same curved500 scenarios without a flag, its closest approach within
    2 % and its largest lateral offset within 10 cm of the 0.01 s loop's."""
    policy = planner_registry.load("safeil")
    summaries = {}
    for step_s in (0.01, 0.1):
        env = gym.make(CURVED, step_s=step_s)
        try:
            for i in (0, 3):
                _, info = env.reset(options={"index": i})
                done = False
                while not done:
                    _, _, te, tr, info = env.step(_plan(policy, info["features"])[0])
                    done = te or tr
                summaries[step_s, i] = env.unwrapped.rollout().summary
        finally:
            env.close()
    for i in (0, 3):
        fine, coarse = summaries[0.01, i], summaries[0.1, i]
        assert coarse["end_reason"] == fine["end_reason"] == "completed"
        assert coarse["flag"] == fine["flag"] == ""
        assert coarse["min_ttc_s"] == pytest.approx(fine["min_ttc_s"], rel=0.02)
        assert coarse["min_gap_m"] == pytest.approx(fine["min_gap_m"], rel=0.02)
        # the coarser tracking swings a little wider (0.13 -> 0.19 m on scenario 0)
        assert fine["max_abs_lateral_offset_m"] - 0.01 <= coarse["max_abs_lateral_offset_m"] \
            <= fine["max_abs_lateral_offset_m"] + 0.1
        assert coarse["steps"] * 10 == pytest.approx(fine["steps"], rel=0.01)


@pytest.mark.sumo
def test_vector_env_gives_the_single_envs_trajectories():
    """make_vec(vector_entry_point): sub-env i with seed s + i, through an autoreset, steps as a
    single env reset with seed s + i then reset again (to 1e-9: the single env runs on floats,
    the vector env on arrays, which differ by round-off)."""
    policy = planner_registry.load("analytic")
    n, steps = 3, 30
    venv = gym.make_vec(CURVED, num_envs=n, vectorization_mode="vector_entry_point",
                        max_time_s=1.5)
    assert isinstance(venv, envs.SafeILVectorEnv)
    assert venv.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    obs, info = venv.reset(seed=5)
    episodes = [[[o]] for o in obs]
    rewards = [[[]] for _ in range(n)]
    try:
        for _ in range(steps):
            obs, r, te, tr, info = venv.step(_plan(policy, info["features"]))
            for i in range(n):
                episodes[i][-1].append(obs[i])
                rewards[i][-1].append(r[i])
                if te[i] or tr[i]:
                    episodes[i].append([])
                    rewards[i].append([])
    finally:
        venv.close()
    env = gym.make(CURVED, max_time_s=1.5)
    try:
        for i in range(n):
            o, inf = env.reset(seed=5 + i)
            single, single_r = [[o]], [[]]
            while len(single) < len(episodes[i]) or len(single[-1]) < len(episodes[i][-1]):
                o, r, te, tr, inf = env.step(_plan(policy, inf["features"])[0])
                single[-1].append(o)
                single_r[-1].append(r)
                if te or tr:
                    o, inf = env.reset()
                    single.append([o])
                    single_r.append([])
            assert len(episodes[i]) >= 2  # an autoreset happened
            for k, ep in enumerate(episodes[i]):
                np.testing.assert_allclose(np.array(ep), np.array(single[k][:len(ep)]),
                                           rtol=0, atol=1e-9)
            # the vector env's reward of an autoreset step is 0: the single env has no step
            got_r = [r for ep in rewards[i] for r in ep]
            want_r = []
            for k, ep in enumerate(rewards[i]):
                want_r += ([0.0] if k else []) + single_r[k][:len(ep) - (1 if k else 0)]
            np.testing.assert_allclose(got_r, want_r, rtol=0, atol=1e-9)
    finally:
        env.close()


@pytest.mark.sumo
def test_vector_env_takes_a_seed_per_sub_env():
    """``reset(seed=[s_0, ..., s_{n-1}])`` seeds each sub-env (as gymnasium's SyncVectorEnv):
    ``[5, 6]`` is ``seed=5``'s episodes. The vector env's own generator takes ints only, so
    the list once reached it and gymnasium refused it ("Seed must be a python integer")."""
    venv = envs.SafeILVectorEnv(2, max_time_s=1.0)
    try:
        by_list, _ = venv.reset(seed=[5, 6])
        indices = venv.indices.copy()
        by_int, _ = venv.reset(seed=5)
        np.testing.assert_array_equal(venv.indices, indices)
        np.testing.assert_array_equal(by_list, by_int)
        venv.reset(seed=np.int64(5))  # a numpy int too
        np.testing.assert_array_equal(venv.indices, indices)
    finally:
        venv.close()


@pytest.mark.sumo
def test_traci_envs_run_side_by_side_in_one_process():
    """Gymnasium's SyncVectorEnv of traci envs (a SUMO process each, one Python process): the
    sub-envs do not close each other (libsumo's would) and step as the native vector env does
    (traci's positions are rounded in transit: gap to 1e-6 m as in test_closed_loop); closing it
    ends every SUMO."""
    policy = planner_registry.load("analytic")
    before = {p.pid for p in _descendants()}
    sync = gym.make_vec(CURVED, num_envs=2, vectorization_mode="sync", backend="traci",
                        max_time_s=1.0)
    native = gym.make_vec(CURVED, num_envs=2, vectorization_mode="vector_entry_point",
                          max_time_s=1.0)
    try:
        got, info = sync.reset(seed=7)
        want, want_info = native.reset(seed=7)
        sumo = [p for p in _descendants() if p.pid not in before and "sumo" in p.name()]
        # one SUMO per sub-env (the eclipse-sumo wheel's launcher and the binary it starts)
        assert len([p for p in sumo if p.ppid() == os.getpid()]) == 2
        for _ in range(8):
            got, _, te, tr, info = sync.step(_plan(policy, info["features"]))
            want, _, wte, wtr, want_info = native.step(_plan(policy, want_info["features"]))
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
            np.testing.assert_array_equal(te | tr, wte | wtr)
        assert not (te | tr).any()
    finally:
        sync.close()
        native.close()
    _wait_gone(sumo)


@pytest.mark.sumo
def test_control_level_brakes():
    env = gym.make(CURVED, action_level="control", max_time_s=3.0)
    try:
        assert env.action_space.shape == (2,)
        _, info = env.reset(seed=0)
        v0 = info["v"]
        for _ in range(10):
            _, _, _, _, info = env.step(np.array([-4.0, 0.0]))
        assert info["v"] < v0 - 3.0
        log = env.unwrapped.rollout().log
        assert (log["accel_cmd"] == -4.0).all()
    finally:
        env.close()


@pytest.mark.sumo
def test_bad_input_fails_clearly():
    with pytest.raises(gym.error.Error):
        gym.make("safeil_sumo/NoSuchTask-v0")
    with pytest.raises(ValueError, match="unknown scenario option"):
        gym.make(CURVED, no_such_option=1)
    with pytest.raises(ValueError, match="unknown task"):
        envs.SafeILEnv(task="nope")
    with pytest.raises(ValueError, match="action_level"):
        gym.make(CURVED, action_level="pedals")
    with pytest.raises(ValueError, match="render_mode"):
        envs.SafeILEnv(render_mode="ansi")
    with pytest.raises(ValueError, match="render_mode"):
        gym.make_vec(CURVED, num_envs=2, vectorization_mode="vector_entry_point",
                     render_mode="human")
    for bad in (0, -1):
        with pytest.raises(ValueError, match="num_envs"):
            gym.make_vec(CURVED, num_envs=bad, vectorization_mode="vector_entry_point")
    env = envs.SafeILEnv(max_time_s=0.2)
    strict = envs.SafeILEnv(max_time_s=0.2, out_of_space="raise")
    try:
        with pytest.raises(RuntimeError, match="reset"):
            env.step(env.action_space.sample())
        with pytest.raises(ValueError, match="unknown reset option"):
            env.reset(options={"seed": 3})
        env.reset(seed=0)
        with pytest.raises(ValueError, match="finite"):
            env.step(np.full(6, np.nan))
        with pytest.raises(ValueError, match="shape"):
            env.step(np.zeros(4))
        far = np.array([30.0, 0.0, 60.0, 0.0, 900.0, 0.0])  # x3 past the space: clipped
        done = False
        while not done:
            _, _, te, tr, _ = env.step(far)
            done = te or tr
        with pytest.raises(RuntimeError, match="ended"):
            env.step(far)
        strict.reset(seed=0)
        with pytest.raises(ValueError, match="outside the action space"):
            strict.step(far)
    finally:
        env.close()
        strict.close()


@pytest.mark.sumo
def test_render_rgb_array():
    env = gym.make(CURVED, render_mode="rgb_array", max_time_s=1.0)
    try:
        env.reset(seed=0)
        first = env.render()
        env.step(np.array([30.0, 0.0, 60.0, 0.0, 90.0, 0.0]))
        frame = env.render()
        assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
        assert first.shape == frame.shape and frame.std() > 0
    finally:
        env.close()


def _sumo_running() -> bool:
    import libsumo

    try:
        libsumo.simulation.getTime()
    except Exception:  # noqa: BLE001 - "not connected": no simulation
        return False
    return True


@pytest.mark.sumo
def test_close_ends_sumo_and_a_second_env_takes_it_over():
    a, b = envs.SafeILEnv(max_time_s=2.0), envs.SafeILEnv(max_time_s=2.0)
    try:
        a.reset(seed=0)
        assert _sumo_running()
        b.reset(seed=1)  # libsumo: one simulation per process; a's ends, clearly
        with pytest.raises(RuntimeError, match="one simulation per process"):
            a.step(a.action_space.sample())
        b.step(np.array([30.0, 0.0, 60.0, 0.0, 90.0, 0.0]))
        b.close()
        assert not _sumo_running()
        venv = envs.SafeILVectorEnv(2, max_time_s=2.0)
        venv.reset(seed=0)
        assert _sumo_running()
        venv.close()
        assert not _sumo_running()
    finally:
        a.close()
        b.close()


def _descendants() -> list:
    return [p for p in psutil.Process().children(recursive=True) if p.is_running()
            and p.status() != psutil.STATUS_ZOMBIE]


@pytest.mark.sumo
def test_a_killed_worker_leaves_nothing_behind():
    """Async (a libsumo per worker process): kill a worker, the next step fails (no hang),
    close leaves no process. A native vector env on traci in a child process: kill the child,
    its sumo ends."""
    before = {p.pid for p in _descendants()}
    venv = gym.make_vec(CURVED, num_envs=2, vectorization_mode="async", max_time_s=2.0)
    try:
        venv.reset(seed=0)
        workers = [p for p in _descendants() if p.pid not in before]
        assert workers
        os.kill(venv.unwrapped.processes[0].pid, signal.SIGKILL)
        with pytest.raises(Exception):  # noqa: B017 - gymnasium's error of a dead worker
            venv.step(np.tile([30.0, 0.0, 60.0, 0.0, 90.0, 0.0], (2, 1)))
    finally:
        # gymnasium's close may raise on the dead worker's pipe before it terminates the
        # others; closing our ends of the pipes ends them (they exit on EOF)
        with contextlib.suppress(EOFError, BrokenPipeError, ConnectionResetError):
            venv.close(terminate=True)
        for pipe in venv.unwrapped.parent_pipes:
            with contextlib.suppress(OSError):
                pipe.close()
    _wait_gone(workers)

    code = ("import time, safeil_sumo.envs as e; v = e.SafeILVectorEnv(2, backend='traci'); "
            "v.reset(seed=0); print('up', flush=True); time.sleep(60)")
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                             cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        for _ in range(10):  # traci may print its connection retries first
            line = child.stdout.readline().strip()
            if line in ("up", ""):
                break
        assert line == "up"
        sumo = psutil.Process(child.pid).children(recursive=True)
        assert any("sumo" in p.name() for p in sumo)
        child.send_signal(signal.SIGKILL)
        child.wait(10)
        _wait_gone(sumo)
    finally:
        if child.poll() is None:
            child.kill()


def _wait_gone(procs: list, timeout_s: float = 15.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        alive = [p for p in procs if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
        if not alive:
            return
        time.sleep(0.2)
    pytest.fail(f"processes survived: {[p.pid for p in alive]}")


def test_ppo_trains_on_the_vector_env():
    pytest.importorskip("stable_baselines3")
    sys.path.insert(0, str(REPO / "training"))
    try:
        from ppo_vector_env import train
    finally:
        sys.path.remove(str(REPO / "training"))
    model = train(num_envs=4, total_steps=512, n_steps=64, max_time_s=3.0)
    assert model.num_timesteps >= 512


N74 = "safeil_sumo/N74Traffic-v0"
REPLAY = "safeil_sumo/Replay-v0"


def _drive(env, seed, policy, steps):
    """``steps`` decisions of ``policy`` from ``reset(seed=seed)``: observations, rewards,
    infos' gaps."""
    obs, info = env.reset(seed=seed)
    out, rewards, gaps = [obs], [], [info["gap"]]
    for _ in range(steps):
        obs, r, te, tr, info = env.step(_plan(policy, info["features"])[0])
        out.append(obs)
        rewards.append(r)
        gaps.append(info["gap"])
        if te or tr:
            break
    return np.array(out), np.array(rewards), np.array(gaps)


@pytest.mark.sumo
def test_n74_traffic_is_seeded_and_single_only():
    """N74Traffic-v0 (real libsumo, SUMO's traffic leads): reset(seed=s) twice in one process
    gives the same observations, rewards and leaders; another seed other traffic. The native
    vector env refuses num_envs > 1 clearly, before any SUMO starts."""
    policy = planner_registry.load("safeil")
    env = gym.make(N74, traffic="dense", max_time_s=4.0)
    try:
        o1, r1, _ = _drive(env, 1, policy, 40)
        log1 = env.unwrapped.rollout().log
        o2, r2, _ = _drive(env, 1, policy, 40)
        log2 = env.unwrapped.rollout().log
        assert len(r1) == 40 and o1[:, 8].min() < 60.0  # the radar saw SUMO's traffic ahead
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_array_equal(r1, r2)
        np.testing.assert_array_equal(log1[["leader_x", "leader_y", "leader_v"]].to_numpy(),
                                      log2[["leader_x", "leader_y", "leader_v"]].to_numpy())
        o3, _, _ = _drive(env, 2, policy, 40)
        assert not np.array_equal(o1, o3[:len(o1)])
    finally:
        env.close()
    with pytest.raises(ValueError, match="num_envs=1 only"):
        gym.make_vec(N74, num_envs=2, vectorization_mode="vector_entry_point")
    with pytest.raises(ValueError, match="n74_traffic's traffic must be one of"):
        gym.make(N74, traffic="none")
    with pytest.raises(ValueError, match="runs on net 'n74'"):
        gym.make(N74, net="curved500")


def _need_openacc():
    from fixtures_data import OPENACC_DIR, require_file

    require_file(OPENACC_DIR / "JRC-VC_280219_part3.csv.gz")


@pytest.mark.sumo
def test_replay_is_seeded_and_rewards_closeness_to_the_human():
    """Replay-v0 with radar noise (the index is the replay's seed): the same seed the same
    episode twice, another seed another; the default reward is -0.01 x the squared error of
    the gap against the human's at the same time (no flag on this maneuver)."""
    _need_openacc()
    policy = planner_registry.load("safeil")
    env = gym.make(REPLAY, radar_noise_m=0.5, max_time_s=3.0)
    try:
        o1, r1, _ = _drive(env, 11, policy, 100)
        o2, r2, _ = _drive(env, 11, policy, 100)
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_array_equal(r1, r2)
        o3, _, _ = _drive(env, 12, policy, 100)
        assert not np.array_equal(o1, o3)
        _, info = env.reset(seed=0)
        assert info["human_gap"] == pytest.approx(info["gap"], abs=0.01)  # starts as the human
        for _ in range(10):
            _, r, _, _, info = env.step(_plan(policy, info["features"])[0])
            assert r == pytest.approx(-0.01 * (info["gap"] - info["human_gap"]) ** 2, abs=1e-12)
        assert r < 0
    finally:
        env.close()
    net_dir = env.unwrapped.task.net_dir
    assert net_dir.is_dir()
    del env, o1, o2, o3  # the rebuilt net goes with the env
    import gc

    gc.collect()
    assert not net_dir.exists()
    with pytest.raises(ValueError, match="unknown replay option"):
        gym.make(REPLAY, leader_kind="braking")
    with pytest.raises(ValueError, match="replay source 'nope'"):
        gym.make(REPLAY, source="nope")
    with pytest.raises(ValueError, match="start_s must be"):
        gym.make(REPLAY, start_s=-1.0)
    with pytest.raises(ValueError, match="unknown maneuver"):
        gym.make(REPLAY, maneuver="no-such-maneuver")
    with pytest.raises(ValueError, match="no net"):
        gym.make(REPLAY, net="curved500")


@pytest.mark.sumo
def test_safeil_through_the_replay_env_reproduces_the_replay_cli(tmp_path, capsys):
    """The shipped safeil driven through Replay-v0 (defaults: OpenACC's paper-like window,
    JRC-VC_280219_part3_f4#1 from 72 s, held out of safeil's training) gives the replay CLI's
    gap RMSE to the human within the golden gap tolerance (1e-6 m), from the env's own info."""
    _need_openacc()
    import pandas as pd

    from safeil_sumo.experiments import maneuver_replay as rp
    from safeil_sumo.learn.checkpoint import held_out_maneuvers
    from safeil_sumo.replay import main as replay_main

    assert replay_main(["--source", "openacc", "--maneuver", "auto", "--policy", "safeil",
                        "--out", str(tmp_path / "cli")]) == 0
    want = pd.read_csv(tmp_path / "cli" / "metrics.csv").iloc[0]
    policy = planner_registry.load("safeil")
    env = gym.make(REPLAY)
    try:
        task = env.unwrapped.task
        assert task.maneuver_id == "JRC-VC_280219_part3_f4#1" and task.start_s == 72.0
        assert task.maneuver_id in held_out_maneuvers(REPO / "safeil_sumo/models/safeil.json")
        _, info = env.reset(options={"index": 0})  # the CLI's --seed 0
        t, gap, human = [info["t"]], [info["gap"]], [info["human_gap"]]
        done = False
        while not done:
            _, _, te, tr, info = env.step(_plan(policy, info["features"])[0])
            t.append(info["t"])
            gap.append(info["gap"])
            human.append(info["human_gap"])
            done = te or tr
        assert info["end_reason"] == want["end_reason"] == "timeout"
        np.testing.assert_allclose(t, task.human_t, rtol=0, atol=1e-9)  # 10 Hz, as recorded
        rmse = float(np.sqrt(np.mean((np.array(gap) - np.array(human)) ** 2)))
        assert rmse == pytest.approx(want["rmse_gap"], abs=1e-6)
        # and the CLI's own comparison of the env's log
        human_trace = pd.DataFrame({"t": task.human_t, "gap": task.human_gap})
        trace = rp.policy_trace(env.unwrapped.rollout().log, pd.read_parquet(
            tmp_path / "cli" / "human.parquet"))
        got = rp.compare(pd.read_parquet(tmp_path / "cli" / "human.parquet"), trace)
        assert got["rmse_gap"] == pytest.approx(want["rmse_gap"], abs=1e-6)
        assert got["rmse_v"] == pytest.approx(want["rmse_v"], abs=1e-6)
        np.testing.assert_allclose(human_trace["gap"], pd.read_parquet(
            tmp_path / "cli" / "human.parquet")["gap"], rtol=0, atol=1e-9)
    finally:
        env.close()


def test_the_single_envs_float_path_equals_the_array_path():
    """The single env's reward, info and observation on floats (reward_one, info_one,
    observe_one) equal the vector env's array functions, bit for bit, on crafted steps: NaN and
    inf features and progress, every flag and end, the replay's gap error, the style's gap error
    (with a style, without one: NaN, and none given)."""
    from types import SimpleNamespace as NS

    from safeil_sumo.envs import spaces as sp

    rng = np.random.default_rng(0)
    cfg = sp.RewardConfig(progress_per_m=0.013, ttc_flag=-1.5, lane_departure=-0.7,
                          collision=-9.0, off_road=-11.0, human_gap_per_m2=-0.02,
                          style_gap_per_m2=-0.03)
    reasons = ["", "completed", "timeout", "collision", "off_road", "flag"]
    for k in range(200):
        feats = rng.normal(0, 60, 9)
        feats[rng.integers(0, 9)] = [np.nan, np.inf, -np.inf, 1e9][k % 4]
        s = rng.choice([rng.uniform(0, 500), np.nan, np.inf])
        gap = rng.choice([rng.uniform(0, 80), np.inf, np.nan])
        obs = NS(t=np.array([0.1 * k]), s=np.array([s]), gap=np.array([gap]),
                 ttc=np.array([rng.uniform(0, 9)]), d=np.array([rng.normal()]),
                 v=np.array([30.0]), leader_v=np.array([29.0]),
                 path_fraction=np.array([0.5]), features=feats[None],
                 lane_departure=np.array([k % 2 == 0]), ttc_flag=np.array([k % 3 == 0]),
                 collision=np.array([k % 5 == 0]))
        ev = NS(lane_departure=np.array([k % 2 == 1]), ttc_flag=np.array([k % 3 == 1]),
                collision=np.array([k % 7 == 0]),
                end_reason=np.array([reasons[k % 6]], object),
                sub_steps=np.array([0 if k % 11 == 0 else 10]))
        before = rng.uniform(0, 400)
        style = sp.style_gaps(np.array([rng.uniform(0.5, 3.0)]), np.array([rng.uniform(-5, 9)]),
                              obs.v)
        for human, styled in itertools.product(
                (None, np.array([rng.uniform(0, 80)])), (None, np.array([np.nan]), style)):
            want = cfg.rewards(np.array([before]), obs, ev, human, styled)[0]
            got = cfg.reward_one(before, obs, ev, None if human is None else human[0],
                                 None if styled is None else float(styled[0]))
            assert got == want or (np.isnan(got) and np.isnan(want)), (k, got, want)
            arrays = {key: v[0] for key, v in sp.infos(obs, ev, human, styled).items()}
            floats = sp.info_one(obs, ev, None if human is None else human[0],
                                 None if styled is None else float(styled[0]))
            assert arrays.keys() == floats.keys()
            for key, value in arrays.items():
                np.testing.assert_array_equal(floats[key], value, err_msg=key)
        got_obs = sp.observe_one(feats)
        np.testing.assert_array_equal(got_obs, sp.observe(feats[None])[0])
        assert got_obs.dtype == np.float32


def test_the_style_reward_term_by_hand():
    """``style_gap_per_m2`` times the squared gap error against s0 + T v, capped at 100 m (also
    with no leader seen); 0 by default, and never where no style is set (NaN)."""
    from types import SimpleNamespace as NS

    from safeil_sumo.envs import spaces as sp

    assert sp.RewardConfig().style_gap_per_m2 == 0.0
    v = np.array([20.0, 20.0, 20.0, 20.0])
    style = sp.style_gaps(np.array([1.5, 1.5, np.nan, 1.5]), np.array([2.0, 2.0, 2.0, 2.0]), v)
    np.testing.assert_array_equal(style[[0, 1, 3]], 32.0)  # 2 m + 1.5 s x 20 m/s
    assert np.isnan(style[2])
    obs = NS(s=np.zeros(4), gap=np.array([30.0, 250.0, 30.0, np.inf]), v=v)
    ev = NS(ttc_flag=np.zeros(4, bool), lane_departure=np.zeros(4, bool),
            collision=np.zeros(4, bool), end_reason=np.array([""] * 4, object),
            sub_steps=np.full(4, 10))
    cfg = sp.RewardConfig(progress_per_m=0.0, style_gap_per_m2=-0.02)
    # (30 - 32)^2 = 4 m^2; |250 - 32| capped at 100 m; no style; no leader: capped
    np.testing.assert_allclose(cfg.rewards(np.zeros(4), obs, ev, style_gap=style),
                               [-0.08, -200.0, 0.0, -200.0], rtol=1e-15)
    np.testing.assert_array_equal(sp.RewardConfig(progress_per_m=0.0).rewards(
        np.zeros(4), obs, ev, style_gap=style), 0.0)


def _style_episode(env, steps: int, style_at: dict, seed: int = 3):
    """Rewards and infos of one episode of ``env`` driven by the analytic planner's plans;
    ``style_at``: step k -> (T, s0) or None, set before step k."""
    policy = planner_registry.load("analytic")
    _, info = env.reset(seed=seed)
    rewards, infos = [], []
    for k in range(steps):
        if k in style_at:
            style = style_at[k]
            env.unwrapped.set_style(*((None,) if style is None else style))
        _, r, te, tr, info = env.step(_plan(policy, info["features"])[0])
        rewards.append(r)
        infos.append(info)
        assert not (te or tr)
    return np.array(rewards), infos


@pytest.mark.sumo
def test_set_style_changes_the_style_gap_and_the_reward_by_hand():
    """The single env: a style set before step 5 shows in that step's info["style_gap"] as
    s0 + T v (v: info["v"], the step's end) and changes its reward by w (gap - style gap)^2
    against the same episode without a style; cleared before step 10, the reward is the
    unstyled one again, bit for bit, and the key is gone. The reset option sets it too."""
    w, T, s0 = -0.01, 2.0, 4.0
    env = gym.make(CURVED, max_time_s=3.0, reward={"style_gap_per_m2": w})
    try:
        plain, plain_infos = _style_episode(env, 15, {})
        styled, infos = _style_episode(env, 15, {5: (T, s0), 10: None})
        assert env.unwrapped.style is None
        for k in range(15):
            on = 5 <= k < 10
            info = infos[k]
            assert info["gap"] == plain_infos[k]["gap"]  # the style changes no part of the loop
            assert "style_gap" not in plain_infos[k]
            if not on:
                assert "style_gap" not in info and styled[k] == plain[k]
                continue
            assert info["style_gap"] == s0 + T * info["v"]
            e = info["gap"] - (s0 + T * info["v"])
            assert abs(e) > 10.0  # 50 m at 30 m/s against ~64 m: a term worth checking
            assert styled[k] - plain[k] == pytest.approx(w * e * e, rel=1e-12)
        _, info = env.reset(seed=3, options={"style": {"time_gap_s": T}})  # s0 0 m
        assert env.unwrapped.style == {"time_gap_s": T, "standstill_m": 0.0}
        assert info["style_gap"] == T * info["v"]
        _, info = env.reset(seed=3)  # kept until changed
        assert info["style_gap"] == T * info["v"]
        _, info = env.reset(seed=3, options={"style": None})
        assert "style_gap" not in info
    finally:
        env.close()


@pytest.mark.sumo
def test_the_vector_envs_style_is_per_sub_env():
    """Two sub-envs on the same episode: the style set for sub-env 1 only shows in its
    info["style_gap"] (sub-env 0's is NaN and masked out) and changes its reward alone, by
    w (gap - (s0 + T v))^2; the constructor's style is every sub-env's, and a reset option
    sets each."""
    w, T, s0 = -0.01, 1.5, 2.0
    policy = planner_registry.load("analytic")
    venv = envs.SafeILVectorEnv(2, max_time_s=2.0, reward={"style_gap_per_m2": w},
                                style={"time_gap_s": 3.0, "standstill_m": 1.0})
    try:
        assert venv.styles == [{"time_gap_s": 3.0, "standstill_m": 1.0}] * 2
        _, info = venv.reset(options={"index": [4, 4], "style": [None, None]})
        assert np.isnan(info["style_gap"]).all() and not info["_style_gap"].any()
        for k in range(8):
            if k == 3:
                venv.set_style(T, s0, index=1)
                assert venv.styles == [None, {"time_gap_s": T, "standstill_m": s0}]
            _, r, _, _, info = venv.step(_plan(policy, info["features"]))
            assert np.isnan(info["style_gap"][0]) and not info["_style_gap"][0]
            assert info["_style_gap"][1] == (k >= 3)
            if k < 3:
                assert np.isnan(info["style_gap"][1])
                assert r[1] == pytest.approx(r[0], abs=1e-9)
                continue
            assert info["style_gap"][1] == s0 + T * info["v"][1]
            e = info["gap"][1] - info["style_gap"][1]
            assert r[1] - r[0] == pytest.approx(w * e * e, rel=1e-6)
        _, info = venv.reset(options={"index": [4, 4], "style": {"time_gap_s": 2.0}})
        np.testing.assert_array_equal(info["style_gap"], 2.0 * info["v"])
        assert info["_style_gap"].all()
    finally:
        venv.close()


def test_a_bad_style_is_refused_before_sumo_starts():
    for bad, error, match in (
            ({"time_gap_s": 0.0}, ValueError, r"\(0, 10\] s"),
            ({"time_gap_s": float("nan")}, ValueError, r"\(0, 10\] s"),
            ({"time_gap_s": 1.5, "standstill_m": 50.0}, ValueError, "standstill_m must be in"),
            ({"time_gap": 1.5}, ValueError, "takes time_gap_s"),
            ({"standstill_m": 2.0}, ValueError, "takes time_gap_s"),
            ({"time_gap_s": "x"}, ValueError, "numbers"),
            ("1.5", TypeError, "a dict")):
        with pytest.raises(error, match=match):
            envs.SafeILEnv(style=bad)
        with pytest.raises(error, match=match):
            envs.SafeILVectorEnv(2, style=bad)
    env = envs.SafeILEnv(max_time_s=0.2)
    venv = envs.SafeILVectorEnv(2, max_time_s=0.2)
    with pytest.raises(ValueError, match=r"\(0, 10\] s"):
        env.set_style(-1.0)
    with pytest.raises(ValueError, match="standstill_m must be in"):
        venv.set_style(1.5, 40.0)
    for index in (2, -1, True, 0.5):
        with pytest.raises(ValueError, match="sub-env in"):
            venv.set_style(1.5, index=index)
    with pytest.raises(ValueError, match="one style or 2"):
        venv.reset(options={"style": [{"time_gap_s": 1.0}]})
    with pytest.raises(ValueError, match="takes time_gap_s"):
        env.reset(options={"style": {"gap": 1.0}})
    assert env.style is None and venv.styles == [None, None]
