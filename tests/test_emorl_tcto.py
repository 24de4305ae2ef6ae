"""EMORL-TCTO: the Pareto archive and hypervolume on hand sets, the improvement model and the prediction-guided
choice on hand cases, the weighted reward of the environment, learning (value loss on a fixed batch), checkpoints
that resume exactly mid-generation, actions, the manifest's days, seeds, and the rule that picks the executed
member."""
import copy
import dataclasses

import numpy as np
import pytest
import torch

from dswm.config import ConfigError
from dswm.methods.base import DayContext
from dswm.methods.emorl_tcto import EMORLTCTOController, EMORLTCTOSettings
from dswm.methods.emorl_tcto.archive import hypervolume, non_dominated, select_member, warmup_weights, weight_lattice
from dswm.methods.emorl_tcto.controller import CHECKPOINT
from dswm.methods.emorl_tcto.objectives import (ObjectiveVecEnv, make_policy, max_energy_ratio, policy_actions,
                                                step_objectives)
from dswm.methods.emorl_tcto.prediction import fit_improvement, neighbour_weights, select_tasks
from dswm.methods.emorl_tcto.training import EVAL_STREAM, Evolution, initial_policy
from dswm.methods.rl.spaces import flat_observation
from dswm.protocol.evaluation import evaluate
from dswm.sim.core import FleetCore, Grid, fleet_state_from_obs, initial_positions
from dswm.sim.env import synthetic_demand
from dswm.sim.fleet import ACTIVE
from prep.tensor import DemandTensor, GridSpec

GRID = Grid(rows=6, cols=6, cell_m=235.0)
K = 3
DAY_IDS = np.array([2, 5, 7, 9])  # tensor days of the core's 4 training days
LABELS = ["d2", "d5", "d7", "d9"]
HORIZON = 143
OPTIONS = {"n_population": 2, "warmup_rounds": 1, "generations": 1, "task_rounds": 1, "weight_divisions": 2,
           "prediction_bandwidth": 0.5, "prediction_ridge": 0.1, "eval_days": 2,
           "select_rule": "best_served_ratio", "select_weight": [1.0, 0.0, 0.0],
           "n_envs": 2, "net_arch": [32, 32], "learning_rate": 1.0e-3, "gamma": 0.9, "batch_size": 143,
           "n_epochs": 4, "gae_lambda": 0.95, "clip_range": 0.2, "ent_coef": 0.0, "vf_coef": 0.5,
           "max_grad_norm": 0.5, "log_std_init": -0.5, "checkpoint_every": 1}
TASKS = 2 * (1 + 1)  # n_population x (warm-up + generations)


@pytest.fixture(scope="module")
def small(scenario):
    return dataclasses.replace(scenario, n_uavs=K)


def make_core(small) -> FleetCore:
    demand = synthetic_demand(days=4, rows=6, cols=6, slots=small.slots_per_day, seed=3)
    core = FleetCore(demand=demand, grid=GRID, scenario=small, dataset="toy", day_labels=LABELS,
                     init_pos=initial_positions(demand.mean(axis=(0, 1)), GRID, K, 0))
    core.day_ids = DAY_IDS
    return core


def settings(**changes) -> EMORLTCTOSettings:
    return EMORLTCTOController.options_from_plain(name="emorl_tcto", data={**OPTIONS, **changes})


def controller(seed=0, **changes) -> EMORLTCTOController:
    return EMORLTCTOController(name="emorl_tcto", seed=seed, device="cpu", options=settings(**changes))


def fit(small, run_dir, seed=0, **changes):
    torch.set_num_threads(1)
    ctl = controller(seed, **changes)
    return ctl, ctl.fit(make_core(small), run_dir=run_dir)


@pytest.fixture(scope="module")
def fitted(small, tmp_path_factory):
    """One run: 2 warm-up tasks and one generation of 2 tasks, one round of 2 days each, a checkpoint per task."""
    run_dir = tmp_path_factory.mktemp("emorl")
    return (*fit(small, run_dir), run_dir)


def contexts(small, days):
    core = make_core(small)
    return [DayContext(dataset="toy", day=int(d), label=LABELS[d], split="id", grid=GRID, scenario=small,
                       geometry=GRID.geometry(), cells=GRID.cells(), init_pos=core.init_pos.numpy()) for d in days]


def run_actions(ctl, small, days, slots):
    """Actions of ``ctl`` over ``slots`` slots of ``days``, and the largest move of an active UAV."""
    core = make_core(small)
    obs = core.reset(days)
    ctl.reset_batch(contexts(small, days))
    actions, largest = [], 0.0
    for _ in range(slots):
        a = ctl.act_batch(obs)
        before = fleet_state_from_obs(obs["fleet"], GRID, small)
        obs = core.step(a).obs
        after = fleet_state_from_obs(obs["fleet"], GRID, small)
        moved = torch.linalg.vector_norm(after.pos - before.pos, dim=-1)[before.status == ACTIVE]
        largest = max(largest, float(moved.max()))
        actions.append(a)
    return np.stack(actions), largest


# ----------------------------------------------------------------------------------- archive and weights

def test_archive_keeps_exactly_the_non_dominated_points_first_of_duplicates():
    points = [(0.7, -1.0, 0.90),  # 0 kept
              (0.6, -0.9, 0.90),  # 1 kept: better energy than 0
              (0.7, -1.0, 0.90),  # 2 duplicate of 0: dropped, the first stays
              (0.7, -1.0, 0.85),  # 3 equal to 0 in two objectives, worse in one: dominated
              (0.5, -0.95, 0.80),  # 4 dominated by 1
              (0.4, -0.8, 0.95),  # 5 kept: best energy and Jain
              (0.6, -0.9, 0.90)]  # 6 duplicate of 1: dropped
    assert non_dominated(points) == [0, 1, 5]
    order = [6, 4, 2, 5, 3, 1, 0]  # the same set in another order: the first copy of each front point stays
    assert [order[i] for i in non_dominated([points[i] for i in order])] == [6, 2, 5]
    assert non_dominated(np.zeros((0, 3))) == []
    with pytest.raises(ValueError, match="non-finite"):
        non_dominated([(0.5, np.nan, 0.5)])


def test_hypervolume_of_hand_boxes():
    ref = (0.0, -2.0, 0.0)
    assert hypervolume([(0.7, -1.0, 0.9)], ref) == pytest.approx(0.7 * 1.0 * 0.9)
    # two boxes minus their overlap [0, 0.5] x [-2, -1] x [0, 0.5]
    assert hypervolume([(0.7, -1.0, 0.9), (0.5, -0.5, 0.5)], ref) == pytest.approx(0.63 + 0.375 - 0.25)
    assert hypervolume([(0.7, -1.0, 0.9), (0.6, -1.0, 0.8)], ref) == pytest.approx(0.63)  # a dominated point adds 0


def test_weight_lattice_and_warmup_weights_spread_from_the_served_ratio_corner(small):
    lattice = weight_lattice(2)
    assert lattice.shape == (6, 3) and np.allclose(lattice.sum(axis=1), 1.0)
    assert {tuple(w) for w in lattice} == {(1, 0, 0), (0, 1, 0), (0, 0, 1), (.5, .5, 0), (.5, 0, .5), (0, .5, .5)}
    assert warmup_weights(3, 4).tolist() == [[1, 0, 0], [0, 0, 1], [0, 1, 0]]
    assert warmup_weights(4, 4).tolist()[3] == [0, 0.5, 0.5]  # the point farthest from the three corners
    assert max_energy_ratio(small) >= 1.0


def test_select_member_picks_the_row_its_rule_states():
    f = [(0.70, -1.00, 0.90), (0.60, -0.90, 0.95), (0.70, -0.95, 0.80)]
    assert select_member(f, "best_served_ratio") == 0  # tie with row 2: the first (older) member
    assert select_member(f, "max_scalarized", (0.0, 0.0, 1.0)) == 1
    assert select_member(f, "max_scalarized", (0.0, 1.0, 0.0)) == 1
    assert select_member(f, "max_scalarized", (1.0, 1.0, 0.0)) == 2  # 0.70 - 0.95 is the largest sum


# ----------------------------------------------------------------------------------- prediction

def test_improvement_model_recovers_a_linear_relation_and_ridge_shrinks_the_slope():
    w = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0]], dtype=float)
    intercept, slope = np.array([-0.02, 0.001, 0.01]), np.array([0.05, 0.002, -0.03])
    d = intercept + slope * w
    model = fit_improvement(w, d, ridge=0.0)
    np.testing.assert_allclose(model.intercept, intercept, atol=1e-12)
    np.testing.assert_allclose(model.slope, slope, atol=1e-12)
    np.testing.assert_allclose(model.predict([[0.25, 0.25, 0.5]]), [intercept + slope * [0.25, 0.25, 0.5]])
    shrunk = fit_improvement(w, d, ridge=1.0)
    assert np.all(np.abs(shrunk.slope) < np.abs(slope)) and np.all(np.sign(shrunk.slope) == np.sign(slope))
    one = fit_improvement(w[:1], d[:1], ridge=0.0)  # one pair: no slope, the change itself
    assert np.array_equal(one.slope, np.zeros(3)) and np.allclose(one.intercept, d[0])
    only_last = fit_improvement(w, d, ridge=0.0, sample_weight=[0, 0, 0, 1])
    np.testing.assert_allclose(only_last.predict(w), np.tile(d[3], (4, 1)))
    assert np.array_equal(fit_improvement(np.zeros((0, 3)), np.zeros((0, 3)), 0.1).predict(w), np.zeros((4, 3)))


def test_neighbour_weights_are_gaussian_in_range_scaled_objective_space():
    k = neighbour_weights([(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 0.3)], (0.0, 0.0, 0.0),
                          scale=(2.0, 0.0, 0.6), bandwidth=0.5)
    np.testing.assert_allclose(k, [1.0, np.exp(-0.5), np.exp(-0.5)])  # z = 0.5 on one axis; a zero range counts 1


def test_selection_picks_the_task_with_the_largest_predicted_hypervolume():
    archive = np.array([(0.7, -1.0, 0.9), (0.6, -0.9, 0.9)])
    weights = np.eye(3)
    predicted = np.array([[(0.8, -1.0, 0.9), (0.7, -1.0, 0.9), (0.7, -1.0, 0.95)],
                          [(0.65, -0.9, 0.9), (0.6, -0.5, 0.9), (0.6, -0.9, 0.9)]])
    ref = (0.0, -2.0, 0.0)
    # gains over the archive: member 1 with the energy weight adds 0.6 x 0.4 x 0.9 = 0.216, the most; then, with
    # that point in, member 0 with the served-ratio weight adds 0.1 x 1.0 x 0.9 = 0.09 (its Jain weight 0.035)
    tasks = select_tasks(archive, predicted, weights, 2, ref)
    assert [(t.parent, t.weight) for t in tasks] == [(1, 1), (0, 0)]
    assert np.array_equal(tasks[0].predicted, predicted[1, 1])
    third = select_tasks(archive, predicted, weights, 3, ref)[2]
    assert (third.parent, third.weight) == (0, 2)


def test_selection_falls_back_on_the_predicted_points_own_volume_when_no_point_enlarges_the_front():
    archive = np.array([(0.7, -1.0, 0.9)])
    predicted = np.array([[(0.65, -1.0, 0.9), (0.6, -1.1, 0.88), (0.69, -1.0, 0.89)]])  # all dominated
    # volumes above (0, -2, 0): 0.65 x 1.0 x 0.9 = 0.585, 0.6 x 0.9 x 0.88 = 0.4752, 0.69 x 1.0 x 0.89 = 0.6141
    tasks = select_tasks(archive, predicted, np.eye(3), 3, (0.0, -2.0, 0.0))
    assert [(t.parent, t.weight) for t in tasks] == [(0, 2), (0, 0), (0, 1)]
    with pytest.raises(ValueError, match="n_tasks"):
        select_tasks(archive, predicted, np.eye(3), 4, (0.0, -2.0, 0.0))


# ----------------------------------------------------------------------------------- environment

def test_the_learner_sees_the_weighted_objectives_and_every_days_mean_is_logged(small):
    env = ObjectiveVecEnv(make_core(small), n_envs=2, seed=4)
    env.weight = np.array([0.2, 0.3, 0.5])
    days = np.random.default_rng(4).integers(4, size=2)
    ref = make_core(small)
    env.reset()
    ref.reset(days)
    norm = ref.hover_energy_j * K
    rng, total = np.random.default_rng(1), np.zeros((2, 3))
    for _ in range(HORIZON):
        a = rng.uniform(-1, 1, (2, 3 * K)).astype(np.float32)
        _, reward, _, _ = env.step(a)
        out = ref.step(a.reshape(2, K, 3))
        obj = np.stack([out.sr, -out.energy_j / norm, out.jain], axis=1)
        total += obj
        np.testing.assert_allclose(reward, (obj @ [0.2, 0.3, 0.5]).astype(np.float32), rtol=1e-6)
        np.testing.assert_allclose(step_objectives(out, norm), obj)
    assert obj[:, 1].min() < -0.1  # the energy term is there and negative
    assert len(env.objective_log) == 2
    np.testing.assert_allclose(np.stack(env.objective_log), total / HORIZON, rtol=1e-6)
    assert env.episode_days() == DAY_IDS[days].tolist()


# ----------------------------------------------------------------------------------- learning

def test_ppo_lowers_its_value_loss_on_a_fixed_batch(small, tmp_path):
    """One policy trained on the served-ratio weight (the first warm-up weight) for 3 rounds of 2 days."""
    ctl, man = fit(small, tmp_path, n_population=1, warmup_rounds=3, generations=0)
    assert man["steps"] == 3 * 4 * 2  # rounds x epochs x minibatches
    core, gamma = make_core(small), OPTIONS["gamma"]
    obs, rng, states, rewards = core.reset([0, 3]), np.random.default_rng(5), [], []
    for _ in range(HORIZON):
        states.append(flat_observation(obs))
        out = core.step(rng.uniform(-1, 1, (2, K, 3)).astype(np.float32))
        rewards.append(out.sr)  # the reward under the weight (1, 0, 0)
        obs = out.obs
    returns, acc = np.zeros((HORIZON, 2)), np.zeros(2)
    for t in reversed(range(HORIZON)):
        acc = rewards[t] + gamma * acc
        returns[t] = acc
    x = torch.as_tensor(np.stack(states)[:100].reshape(-1, states[0].shape[1]))  # far from the day's end
    target = returns[:100].reshape(-1)

    def value_loss(policy):
        with torch.no_grad():
            return float(np.mean((policy.predict_values(x).numpy().reshape(-1) - target) ** 2))

    s = ctl.settings
    assert len(ctl.archive) == 1 and ctl.archive[0]["weight"] == [1.0, 0.0, 0.0]
    trained = make_policy(GRID, small, net_arch=s.net_arch, log_std_init=s.log_std_init, learning_rate=1e-3)
    trained.load_state_dict(ctl.archive[0]["policy"])
    before, after = value_loss(initial_policy(core, s, 0, 0)), value_loss(trained)
    assert before > 10.0
    assert after < 0.4 * before


# ----------------------------------------------------------------------------------- checkpoints and files

def test_checkpoint_mid_generation_resumes_to_the_uninterrupted_run(small, fitted, tmp_path, monkeypatch):
    ctl_a, man_a, _ = fitted
    calls = []
    run_task = Evolution.run_task

    def interrupted(self):
        calls.append(1)
        if len(calls) == TASKS:  # stop before the last task: the generation's plan has one task left
            raise KeyboardInterrupt
        return run_task(self)

    monkeypatch.setattr(Evolution, "run_task", interrupted)
    with pytest.raises(KeyboardInterrupt):
        fit(small, tmp_path)
    state = torch.load(tmp_path / CHECKPOINT, weights_only=False)
    assert state["tasks_done"] == TASKS - 1 and len(state["plan"]) == 1 and state["generation"] == 1
    calls.clear()
    ctl_c, man_c = fit(small, tmp_path)  # a new process would do the same: everything comes from the file
    assert len(calls) == 1  # only the remaining task was trained
    assert man_c["days"] == man_a["days"] and man_c["steps"] == man_a["steps"]
    assert man_c["history"].keys() == man_a["history"].keys()
    for name, values in man_a["history"].items():
        np.testing.assert_array_equal(man_c["history"][name], values, err_msg=name)
    assert [m["id"] for m in ctl_c.archive] == [m["id"] for m in ctl_a.archive]
    for a, c in zip(ctl_a.archive, ctl_c.archive):
        assert (a["parent"], a["generation"], a["weight"], a["objectives"]) == \
            (c["parent"], c["generation"], c["weight"], c["objectives"])
        for key, value in a["policy"].items():
            assert torch.equal(c["policy"][key], value), (a["id"], key)


def test_model_file_round_trips_and_loading_leaves_the_rngs_alone(small, fitted, tmp_path):
    ctl, _, _ = fitted
    path = tmp_path / "model.pt"
    ctl.save(path)
    state = np.random.get_state()[1].copy(), torch.get_rng_state().clone()
    other = controller(seed=5)
    other.load(path)
    assert np.array_equal(np.random.get_state()[1], state[0]) and torch.equal(torch.get_rng_state(), state[1])
    a, _ = run_actions(ctl, small, [0, 2], 5)
    b, _ = run_actions(other, small, [0, 2], 5)
    assert np.array_equal(a, b)
    with pytest.raises(ValueError, match="widths"):
        controller(net_arch=[16]).load(path)
    torch.save({"meta": {"format": "other"}}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="not an EMORL-TCTO model file"):
        controller().load(tmp_path / "bad.pt")


# ----------------------------------------------------------------------------------- acting, manifest, seeds

def test_actions_are_in_range_and_no_uav_moves_more_than_d_max(small, fitted):
    actions, largest = run_actions(fitted[0], small, [0, 1, 2, 3], 20)
    assert actions.shape == (20, 4, K, 3) and actions.dtype == np.float32
    assert actions.min() >= -1.0 and actions.max() <= 1.0
    assert np.abs(actions).max() > 0.01  # the policy acts
    assert largest <= small.d_max_m + 1e-3
    one = fitted[0]
    one.reset(contexts(small, [1])[0])
    core = make_core(small)
    obs = core.reset([1])
    assert np.array_equal(one.act({k: v[0] for k, v in obs.items()}), one.act_batch(obs)[0])
    with pytest.raises(ValueError, match="grid"):
        one.reset_batch([dataclasses.replace(contexts(small, [0])[0], grid=Grid(rows=5, cols=6, cell_m=235.0))])


def test_manifest_lists_every_day_episode_of_every_member_in_order(fitted):
    ctl, man, run_dir = fitted
    draws = np.random.default_rng(0)  # the environment's day draws: one round of 2 days per task
    rounds = [draws.integers(4, size=2).tolist() for _ in range(TASKS)]
    measured = sorted(np.random.default_rng([0, EVAL_STREAM]).choice(4, size=2, replace=False).tolist())
    rows = measured + measured  # the two initial policies are measured first
    for r in rounds:
        rows += r + measured  # each task's training round, then its child's measurement
    assert man["days"] == DAY_IDS[rows].tolist() and set(man["days"]) <= set(DAY_IDS.tolist())
    assert man["day_labels"] == [LABELS[r] for r in rows]
    assert man["n_transitions"] == HORIZON * len(man["days"]) == HORIZON * (2 * 2 + TASKS * 4)
    assert man["transitions_per_day_episode"] == HORIZON and man["read_test_data"] is False
    assert man["checkpoint"] == str(run_dir / CHECKPOINT) and (run_dir / CHECKPOINT).is_file()
    assert man["steps"] == TASKS * 4 * 2  # rounds x epochs x minibatches
    history = man["history"]
    assert history["step"] == [2 * HORIZON * (i + 1) for i in range(TASKS)]
    assert all(len(v) == TASKS for v in history.values())
    assert np.isfinite(history["train/value_loss"]).all() and np.isfinite(history["rollout/ep_rew_mean"]).all()
    assert np.isfinite(history["rollout/task_served_ratio"]).all()
    assert np.isnan(history["rollout/prediction_error_sr"][:2]).all()  # warm-up tasks have no prediction
    assert np.isfinite(history["rollout/prediction_error_sr"][2:]).all()
    assert history["rollout/archive_size"][-1] == len(ctl.archive) >= 1


def test_same_seed_same_actions_after_fit(small, fitted, tmp_path):
    again, _ = fit(small, tmp_path / "again")
    other, _ = fit(small, tmp_path / "other", seed=1)
    a, _ = run_actions(fitted[0], small, [1, 3], 6)
    b, _ = run_actions(again, small, [1, 3], 6)
    c, _ = run_actions(other, small, [1, 3], 6)
    assert np.array_equal(a, b)
    assert np.abs(a - c).max() > 1e-3


def test_a_day_scores_the_same_batched_and_alone_in_the_evaluation(small, fitted):
    demand = synthetic_demand(days=5, rows=6, cols=6, slots=small.slots_per_day, seed=8)
    days = [{"index": i, "label": f"d{i}", "split": "train" if i < 2 else "test", "weekday": i % 7,
             "weekend": False} for i in range(5)]
    meta = {"dataset": "toy", "source": "demo", "days": days, "slots_per_day": 144,
            "eval_days": {"id": [2, 3], "ood": [4]}, "grid": {"rows": 6, "cols": 6, "cell_m": 235.0}}
    tensor = DemandTensor(demand=demand, meta=meta, grid=GridSpec(rows=6, cols=6, cell_m=235.0))
    runs = [evaluate(tensor=tensor, controller=fitted[0], scenario=small, seed=1, limits={"id": None, "ood": None},
                     profile="smoke", device="cpu", batch_days=b, progress_interval_s=5.0).days for b in (True, False)]
    cols = ["day", "sr_mean", "energy_kj_per_slot", "jain"]
    assert runs[0]["day"].to_list() == [2, 3, 4]
    np.testing.assert_allclose(runs[0].select(cols).to_numpy(), runs[1].select(cols).to_numpy(), rtol=1e-6)
    member = float(fitted[0].archive[fitted[0].selected]["id"])
    assert runs[0]["stat_member"].to_list() == runs[1]["stat_member"].to_list() == [member] * 3


# ----------------------------------------------------------------------------------- the executed member

def test_the_select_rule_executes_the_member_it_states(small, fitted, tmp_path):
    ctl, _, _ = fitted
    ctl.save(tmp_path / "model.pt")
    blob = torch.load(tmp_path / "model.pt", weights_only=False)
    first = copy.deepcopy(blob["archive"][0])
    second = copy.deepcopy(first)
    second["policy"]["action_net.bias"] = second["policy"]["action_net.bias"] + 0.3  # another policy
    first["objectives"], second["objectives"] = [0.7, -1.0, 0.9], [0.6, -0.9, 0.95]
    blob["archive"] = [first, second]
    torch.save(blob, tmp_path / "two.pt")
    core = make_core(small)
    obs = core.reset([0, 2])
    expected = []
    for member in (first, second):
        policy = make_policy(GRID, small, net_arch=ctl.settings.net_arch, log_std_init=-0.5, learning_rate=1e-3)
        policy.load_state_dict(member["policy"])
        expected.append(policy_actions(policy, obs, K))
    assert np.abs(expected[0] - expected[1]).max() > 1e-3
    for changes, row in (({"select_rule": "best_served_ratio"}, 0),
                         ({"select_rule": "max_scalarized", "select_weight": [0.0, 0.0, 1.0]}, 1),
                         ({"select_rule": "max_scalarized", "select_weight": [1.0, 0.0, 0.0]}, 0),
                         ({"select_rule": "max_scalarized", "select_weight": [0.0, 1.0, 0.0]}, 1)):
        chosen = controller(**changes)
        chosen.load(tmp_path / "two.pt")
        assert chosen.selected == row, changes
        chosen.reset_batch(contexts(small, [0, 2]))
        assert np.array_equal(chosen.act_batch(obs), expected[row]), changes
        assert chosen.day_stats() == [{"member": float(blob["archive"][row]["id"])}] * 2


def test_fit_executes_the_best_served_ratio_member_of_its_archive(fitted):
    ctl = fitted[0]
    sr = [m["objectives"][0] for m in ctl.archive]
    assert ctl.selected == int(np.argmax(sr))


# ----------------------------------------------------------------------------------- settings

def test_the_rule_is_a_decision_time_setting(small, fitted, tmp_path):
    a = settings(select_rule="best_served_ratio", select_weight=[1.0, 0.0, 0.0])
    b = settings(select_rule="max_scalarized", select_weight=[0.2, 0.3, 0.5])
    train_a, train_b = EMORLTCTOController.training_settings(a), EMORLTCTOController.training_settings(b)
    assert train_a == train_b and train_a.select_rule is None and train_a.select_weight is None
    fitted[0].save(tmp_path / "model.pt")
    bare = EMORLTCTOController(name="emorl_tcto", seed=0, options=train_a)
    bare.load(tmp_path / "model.pt")
    with pytest.raises(RuntimeError, match="select_rule"):
        bare.reset_batch(contexts(small, [0]))


def test_settings_name_the_bad_key(small, tmp_path):
    with pytest.raises(ConfigError, match=r"methods\.emorl_tcto\.n_population.*6 lattice weights"):
        settings(n_population=7)
    with pytest.raises(ConfigError, match=r"methods\.emorl_tcto\.select_weight"):
        settings(select_weight=[0.0, 0.0, 0.0])
    with pytest.raises(ConfigError, match=r"methods\.emorl_tcto\.select_rule"):
        settings(select_rule="best_jain")
    with pytest.raises(ConfigError, match=r"methods\.emorl_tcto\.prediction_bandwidth"):
        settings(prediction_bandwidth=0.0)
    with pytest.raises(ConfigError, match=r"methods\.emorl_tcto\.batch_size.*286"):
        controller(batch_size=100).fit(make_core(small), run_dir=tmp_path)
