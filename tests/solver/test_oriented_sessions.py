"""Several planar or pose sessions of one field, one map (casmag.model.planar and
casmag.model.pose with ``starts``, casmag.solver.staged.solve_sessions,
solve_planar_sessions, solve_pose_sessions, ``casmag slam A.csv B.csv`` on such recordings)."""

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from small_problems import planar_room_field

from casmag.cli.main import main
from casmag.data.imusim import simulate_planar
from casmag.data.posesim import simulate_pose
from casmag.data.recording import read_recording, write_recording
from casmag.errors import DataError
from casmag.model.builder import NoField, build_slam
from casmag.model.planar import PlanarMotion, dead_reckon_planar, dead_reckon_sessions
from casmag.model.pose import PoseMotion, nominal_parameters
from casmag.problem.imu import load_planar_options
from casmag.problem.spec import SolverSpec, load_problem
from casmag.solver.planar import PlanarStaged, solve_planar_recording, solve_planar_sessions

ROOT = Path(__file__).resolve().parents[2]
SETTINGS = [
    "model.sigma_disp=0.002",
    f"model.sigma_dyaw={np.radians(0.05)}",
    "model.gp.num_basis=120",
]


@pytest.mark.parametrize("bias", ["constant", "random_walk"])
def test_the_sessions_cost_is_the_sum_of_each_sessions_cost(bias):
    """Two sessions in one NLP: every block is the sum of the two sessions' own, so no
    odometry, bias walk or anchor term joins them."""
    n1, n2 = 6, 5
    rng = np.random.default_rng(5)
    both = build_slam(PlanarMotion(n1 + n2, bias, (0, n1)), NoField(), SolverSpec())
    alone = [build_slam(PlanarMotion(k, bias), NoField(), SolverSpec()) for k in (n1, n2)]
    walk = bias == "random_walk"
    P, psi = rng.normal(size=(n1 + n2, 2)), rng.normal(size=(n1 + n2, 1))
    rows = [k - 1 if walk else 1 for k in (n1, n2)]
    B = rng.normal(scale=0.1, size=(sum(rows), 1))
    U = rng.normal(size=(n1 + n2 - 1, 3))
    U[n1 - 1] = 1e3  # the step into session 2: never read
    dt = rng.uniform(0.5, 1.5, size=(n1 + n2 - 1, 1))
    anchor = rng.normal(size=(2, 3))
    common = {
        "sigma_disp": 0.3, "sigma_dyaw": 0.2, "sigma_bias0": 0.5, "sigma_anchor": 0.1,
        "sigma_psi0": 0.05, "bias_walk": 0.4,
    }  # fmt: skip
    x = both.x_layout.pack({"P": P, "psi": psi, "bias": B})
    p = both.p_layout.pack({**common, "U": U, "dt": dt, "anchor": anchor})
    total = both.evaluate_blocks(x, p)
    parts: dict[str, float] = {}
    for s, (nlp, a, e) in enumerate(zip(alone, (0, n1), (n1, n1 + n2), strict=True)):
        b_rows = slice(sum(rows[:s]), sum(rows[: s + 1]))
        xs = nlp.x_layout.pack({"P": P[a:e], "psi": psi[a:e], "bias": B[b_rows]})
        ps = nlp.p_layout.pack(
            {**common, "U": U[a : e - 1], "dt": dt[a : e - 1], "anchor": anchor[s : s + 1]}
        )
        for name, v in nlp.evaluate_blocks(xs, ps).items():
            parts[name] = parts.get(name, 0.0) + v
    assert set(total) == set(parts)
    for name in total:
        assert total[name] == pytest.approx(parts[name], rel=1e-12), name


def test_sessions_dead_reckon_from_their_own_starts():
    rng = np.random.default_rng(2)
    U = rng.normal(scale=0.1, size=(9, 3))
    anchors = np.array([[0.0, 0.0, 0.1], [3.0, -1.0, 2.0]])
    P, psi = dead_reckon_sessions(U, anchors, (0, 4))
    P1, psi1 = dead_reckon_planar(U[:3], anchors[0, :2], 0.1)
    P2, psi2 = dead_reckon_planar(U[4:], anchors[1, :2], 2.0)
    np.testing.assert_allclose(P, np.vstack([P1, P2]))
    np.testing.assert_allclose(psi, np.concatenate([psi1, psi2]))


@pytest.fixture(scope="module")
def room_sessions(tmp_path_factory):
    """Session A: three loops of the planar tests' 2 m x 1.5 m room (seed 4, heading-rate
    bias 0.5 deg/s); session B: one loop with another seed and a bias of -1.5 deg/s. One
    field. Measured (model.gp.num_basis 120): A alone 0.091 -> 0.0084 m, B alone 0.105 ->
    0.029 m; together A 0.0070 m, B 0.0103 m."""
    field = planar_room_field()
    folder = tmp_path_factory.mktemp("sessions")
    paths = []
    for name, seed, loops, bias in (("A", 4, 3, 0.5), ("B", 5, 1, -1.5)):
        d = simulate_planar(
            seed, field, size=(2.0, 1.5), loops=loops, heading_bias_deg=bias, disp_noise=0.002
        )
        path = folder / f"{name}.csv"
        write_recording(path, d.t, d.Y, planar=d.U, P_true=d.P, yaw_true=d.psi)
        paths.append(path)
    return paths


def test_extend_starts_a_new_session_from_its_known_start(room_sessions):
    recs = [read_recording(p) for p in room_sessions]
    opts = load_planar_options(None, SETTINGS)
    n1 = recs[0].n_samples
    U = np.vstack([recs[0].increments, np.zeros((1, 3)), recs[1].increments])
    n = U.shape[0] + 1
    anchors = np.array([[*r.P_true[0, :2], r.yaw_true[0]] for r in recs])
    P_dr, _ = dead_reckon_sessions(U, anchors, (0, n1))
    model = PlanarStaged(
        opts, U, np.ones(n - 1), np.vstack([r.Y for r in recs]), anchors[0, :2],
        float(anchors[0, 2]), P_dr, np.zeros(3), 0.01, 0.1, 0.3, 1.0,
        starts=(0, n1), anchors=anchors,
    )  # fmt: skip
    first = {"P": recs[0].P_true[:, :2], "psi": recs[0].yaw_true, "bias": np.array([[0.01]])}
    ext = model.extend(first, n)
    np.testing.assert_array_equal(ext["P"][:n1], recs[0].P_true[:, :2])
    np.testing.assert_allclose(ext["P"][n1:], P_dr[n1:])  # B from its own start, bias 0
    np.testing.assert_array_equal(ext["bias"], [[0.01], [0.0]])
    np.testing.assert_allclose(model.start(n)["P"], P_dr)


@pytest.mark.slow
def test_slam_solves_planar_sessions_and_refuses_mixed_kinds(tmp_path, room_sessions):
    """A second session of the room improves the short one (B) beyond what it reaches
    alone; the session that revisits itself most (A, three loops) is added first."""
    a, b = room_sessions
    out = tmp_path / "out"
    args = ["slam", str(b), str(a), "--out", str(out), "-q"]
    res = CliRunner().invoke(main, args + [f for s in SETTINGS for f in ("--set", s)])
    assert res.exit_code == 0, res.output
    r = json.loads((out / "result.json").read_text())
    assert r["success"] and r["info"]["warm_start"] == "sessions"
    assert r["info"]["session_order"] == [1, 0]
    assert [s["name"] for s in r["info"]["sessions"]] == ["A", "B"]
    assert r["info"]["recordings"] == [str(a), str(b)]
    assert (out / "sessions.png").is_file()
    rows = {row["name"]: row for row in r["info"]["sessions"]}
    alone = solve_planar_recording(b, load_planar_options(None, SETTINGS))
    assert alone.success and rows["B"]["rmse_after"] < 0.6 * alone.rmse_after
    assert rows["A"]["rmse_after"] <= 0.25 * rows["A"]["rmse_before"]
    # Each session's own heading-rate bias, of the sign simulated (rad/s).
    assert rows["A"]["odometry_bias"][0] > 0 > rows["B"]["odometry_bias"][0]
    sessions = [st["session"] for st in r["stages"]]
    assert sessions[0] == 0 and sessions[-1] == 1
    assert sum(st["kept"] for st in r["stages"]) == 1 and r["stages"][-1]["kept"]

    moved = tmp_path / "line.csv"  # a translational recording beside the planar ones
    t = np.arange(20) * 0.1
    P = np.column_stack([t, 0.0 * t])
    Y = np.tile([0.2, 0.0, 0.4], (20, 1)) + 0.01 * np.sin(t)[:, None]
    write_recording(moved, t, Y, dxy=np.diff(P, axis=0), P_true=P)
    res = CliRunner().invoke(main, ["slam", str(a), str(moved), "--out", str(tmp_path / "x")])
    assert res.exit_code != 0
    assert "the sessions of one map share one motion model" in res.output
    assert not (tmp_path / "x" / "result.json").exists()


def test_sessions_need_each_ones_first_pose(tmp_path, room_sessions):
    rec = read_recording(room_sessions[1])
    bare = tmp_path / "bare.csv"
    write_recording(bare, rec.t, rec.Y, planar=rec.increments)
    with pytest.raises(DataError, match="first position and heading"):
        solve_planar_sessions([room_sessions[0], bare])


def test_imu_recordings_without_their_first_poses_are_refused_as_sessions(tmp_path):
    """IMU recordings go to the IMU model's sessions (tests/solver/test_imu_sessions.py),
    which need each one's first true pose: without truth columns, one line naming the
    first recording."""
    t = np.arange(20) * 0.1
    inc = np.tile([1.0, 0.0, 0.0, 0.0, 0.1, 0.0, 0.0], (19, 1))
    Y = np.column_stack([0.2 + 0.01 * np.sin(t), 0.0 * t, 0.4 + 0.0 * t])
    paths = []
    for name in ("i1", "i2"):
        paths.append(tmp_path / f"{name}.csv")
        write_recording(paths[-1], t, Y, imu=inc)
    res = CliRunner().invoke(main, ["slam", *map(str, paths), "--out", str(tmp_path / "o")])
    assert res.exit_code != 0
    assert "i1.csv: several sessions need each one's first position and heading" in res.output


@pytest.mark.slow
def test_a_session_is_also_added_in_growing_prefixes_with_a_random_walk_bias(room_sessions):
    """B (61 samples) is longer than twice first_samples (20): it is also grown in prefixes
    of 20 and 40 samples beside A, each continued by the odometry with its bias so far."""
    a, b = room_sessions
    opts = load_planar_options(
        None,
        [*SETTINGS, "model.bias=random_walk", "solver.warm_start.strategy=none",
         "solver.warm_start.first_samples=20"],
    )  # fmt: skip
    r = solve_planar_sessions([a, b], opts)
    assert r.success and r.info["session_order"] == [0, 1]
    added = [(st["start"], st["samples"]) for st in r.stages if st["session"] == 1]
    n_a = 186
    assert added == [
        ("dead reckoning", n_a + 61),
        ("growing prefixes", n_a + 20),
        ("growing prefixes", n_a + 40),
        ("growing prefixes", n_a + 61),
    ]
    assert sum(st["chosen"] for st in r.stages if st["session"] == 1) == 1
    rows = {row["name"]: row for row in r.info["sessions"]}
    # A random walk: one bias per step within each session, none across the gap.
    assert len(rows["A"]["odometry_bias"]) == n_a - 1 and len(rows["B"]["odometry_bias"]) == 60
    for row in rows.values():
        assert row["rmse_after"] <= 0.25 * row["rmse_before"]


@pytest.mark.parametrize("height", [False, True])
def test_the_pose_sessions_cost_is_the_sum_of_each_sessions_cost(height):
    n1, n2 = 5, 4
    rng = np.random.default_rng(8)
    motion = {"map_dim": 2, "height": height}
    both = build_slam(PoseMotion(n1 + n2, starts=(0, n1), **motion), NoField(), SolverSpec())
    alone = [build_slam(PoseMotion(k, **motion), NoField(), SolverSpec()) for k in (n1, n2)]
    n = n1 + n2
    Q = rng.normal(size=(n, 4))
    Q /= np.linalg.norm(Q, axis=1, keepdims=True)
    x = {"P": rng.normal(size=(n, 3)), "D": rng.normal(scale=0.1, size=(n, 3)),
         "bias_p": rng.normal(size=(2, 3)), "bias_w": rng.normal(size=(2, 3))}  # fmt: skip
    U = np.column_stack([rng.normal(size=(n - 1, 3)), Q[1:]])
    U[n1 - 1] = 1e3  # the step into session 2: never read
    common = {
        "sigma_p": 0.3, "sigma_r": 0.2, "sigma_bp": 0.5, "sigma_bw": 0.4, "sigma_anchor": 0.1,
        "sigma_att0": 0.05, "sigma_height": 0.7,
    }  # fmt: skip
    p = {
        **common, "U": U, "dt": rng.uniform(0.5, 1.5, size=(n - 1, 1)),
        "anchor_p": rng.normal(size=(2, 3)), "anchor_q": Q[[0, n1]],
        **nominal_parameters(Q, (0, n1)),
    }  # fmt: skip
    p["QREL"][n1 - 1] = 1e3  # not read either
    total = both.evaluate_blocks(both.x_layout.pack(x), both.p_layout.pack(p, default=0.0))
    parts: dict[str, float] = {}
    for s, (nlp, a, e) in enumerate(zip(alone, (0, n1), (n1, n), strict=True)):
        xs = {k: v[a:e] if v.shape[0] == n else v[s : s + 1] for k, v in x.items()}
        ps = {
            **common, "U": U[a : e - 1], "dt": p["dt"][a : e - 1],
            "anchor_p": p["anchor_p"][s : s + 1], "anchor_q": p["anchor_q"][s : s + 1],
            **nominal_parameters(Q[a:e]),
        }  # fmt: skip
        values = nlp.evaluate_blocks(nlp.x_layout.pack(xs), nlp.p_layout.pack(ps, default=0.0))
        for name, v in values.items():
            parts[name] = parts.get(name, 0.0) + v
    assert set(total) == set(parts) and ("height" in total) == height
    for name in total:
        assert total[name] == pytest.approx(parts[name], rel=1e-12), name


@pytest.fixture(scope="module")
def pose_halves(tmp_path_factory):
    """A simulated 6-DoF walk (problems/bench/peers.yaml, 200 samples over 4 x 2 m, seed 2,
    rotation-rate bias 0.002 rad/s about z) cut into two recordings of one field: samples
    0-119 and 120-199, each with its truth. Measured: alone 0.192 -> 0.044 m and 0.046 ->
    0.032 m; together 0.034 and 0.030 m."""
    sets = ["seed=2", "simulation.trajectory.samples=200", "simulation.trajectory.area=[4.0, 2.0]"]
    prob = load_problem(ROOT / "problems" / "bench" / "peers.yaml", sets)
    rec = simulate_pose(prob.spec.simulation, 2, bias_w=(0.0, 0.0, 0.002))
    folder = tmp_path_factory.mktemp("pose")
    paths = []
    for name, a, e in (("first", 0, 120), ("second", 120, 200)):
        paths.append(folder / f"{name}.csv")
        write_recording(
            paths[-1], rec.t[a:e], rec.Y[a:e], pose=rec.U[a : e - 1], P_true=rec.P_true[a:e],
            q_true=rec.q_true[a:e],
        )  # fmt: skip
    return paths


@pytest.mark.slow
def test_pose_sessions_share_one_map(tmp_path, pose_halves):
    first, second = pose_halves
    out = tmp_path / "out"
    sets = ["solver.warm_start.first_samples=40", "solver.warm_start.stage_max_iter=10"]
    args = ["slam", str(second), str(first), "--out", str(out), "-q"]
    res = CliRunner().invoke(main, args + [f for s in sets for f in ("--set", s)])
    assert res.exit_code == 0, res.output
    r = json.loads((out / "result.json").read_text())
    assert r["motion"] == "pose" and r["success"] and r["info"]["warm_start"] == "sessions"
    rows = {row["name"]: row for row in r["info"]["sessions"]}
    assert set(rows) == {"first", "second"}
    assert rows["first"]["rmse_after"] <= 0.25 * rows["first"]["rmse_before"]
    assert rows["second"]["rmse_after"] < rows["second"]["rmse_before"]
    assert len(r["info"]["anchor"]["sessions"]) == 2
    assert (out / "sessions.png").is_file()
