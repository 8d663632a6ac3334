"""Property-based checks of the input readers: a malformed recording CSV or a mutated problem
file is either accepted or refused with casmag's own one-line input error (DataError for
recordings, ProblemError for problem files), never any other exception.

Derandomized (the same examples every run) and small enough to run in seconds."""

from __future__ import annotations

import copy
import io
import math
import tempfile
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from casmag.data.recording import read_recording
from casmag.errors import DataError, ProblemError
from casmag.experiments.sweep import load_sweep
from casmag.problem.imu import load_imu_problem, load_planar_options
from casmag.problem.spec import load_problem

ROOT = Path(__file__).resolve().parents[2]
SETTINGS = settings(
    derandomize=True,
    max_examples=120,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)

# Tokens a broken CSV writer, an editor or a hostile file may put in a field.
NUMBERISH = [
    "0", "1", "-0.0", "0.05", "1e-3", "1E3", "+2.5", ".5", "5.", "1e308", "-1e308", "1e309",
    "1e-320", "1e300", "1e101", "9" * 400, "1_000", "nan", "NaN", "inf", "-inf", "Infinity",
    "", " ", "  1 ", "\t2", "0x10", "1e", "--1", "1.2.3", "١٢", "１２", "true", "None", '"1"',
    "1,2", "\u00a01", "1\x00",
]  # fmt: skip
COLUMNS = [
    "t", "dx", "dy", "dz", "dfwd", "dleft", "dyaw", "dqw", "dqx", "dqy", "dqz", "dvx", "dvy",
    "dvz", "mx", "my", "mz", "x_true", "y_true", "z_true", "yaw_true", "qw_true", "qx_true",
    "qy_true", "qz_true", "T", "m x", "", "t ",
]  # fmt: skip
HEADERS = [
    ["t", "dx", "dy", "mx", "my", "mz"],
    ["t", "dx", "dy", "dz", "mx", "my", "mz", "x_true", "y_true", "z_true"],
    ["t", "dfwd", "dleft", "dyaw", "mx", "my", "mz", "x_true", "y_true", "yaw_true"],
    ["t", "dqw", "dqx", "dqy", "dqz", "dvx", "dvy", "dvz", "mx", "my", "mz",
     "qw_true", "qx_true", "qy_true", "qz_true"],
]  # fmt: skip


def _valid_row(header: list[str], k: int) -> list[str]:
    values = {
        "t": 0.1 * k, "dx": 0.05, "dy": 0.01 * (k % 3), "dz": 0.0, "dfwd": 0.05, "dleft": 0.0,
        "dyaw": 0.02, "dqw": 1.0, "dqx": 0.0, "dqy": 0.0, "dqz": 0.0, "dvx": 0.01, "dvy": 0.0,
        "dvz": 0.0, "mx": 0.3 + 0.01 * math.sin(k), "my": -0.1, "mz": 0.5, "x_true": 0.05 * k,
        "y_true": 0.0, "z_true": 0.0, "yaw_true": 0.02 * k, "qw_true": 1.0, "qx_true": 0.0,
        "qy_true": 0.0, "qz_true": 0.0,
    }  # fmt: skip
    return [repr(values.get(c, 0.0)) for c in header]


@st.composite
def recordings(draw: st.DrawFn) -> str:
    """A recording's text: a valid one with a few fields, rows or header names broken."""
    header = list(draw(st.sampled_from(HEADERS)))
    n = draw(st.integers(min_value=0, max_value=8))
    rows = [_valid_row(header, k) for k in range(n)]
    for _ in range(draw(st.integers(min_value=0, max_value=4))):
        kind = draw(st.sampled_from(["field", "field", "field", "header", "row", "width"]))
        if kind == "field" and rows:
            i = draw(st.integers(0, len(rows) - 1))
            if rows[i]:
                j = draw(st.integers(0, len(rows[i]) - 1))
                rows[i][j] = draw(st.sampled_from(NUMBERISH) | st.text(max_size=6))
        elif kind == "header":
            j = draw(st.integers(0, len(header) - 1))
            header[j] = draw(st.sampled_from(COLUMNS))
        elif kind == "row" and rows:
            i = draw(st.integers(0, len(rows) - 1))
            rows.insert(i, draw(st.sampled_from([[], [""], list(rows[i])])))
        elif kind == "width" and rows:
            i = draw(st.integers(0, len(rows) - 1))
            rows[i] = rows[i][:-1] if draw(st.booleans()) else [*rows[i], "0"]
    end = draw(st.sampled_from(["\n", "\r\n", ""]))
    return "\n".join(",".join(r) for r in [header, *rows]) + end


@SETTINGS
@given(text=recordings())
def test_a_malformed_recording_is_read_or_refused_with_one_line(text):
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "rec.csv"
        path.write_bytes(text.encode("utf-8", "surrogatepass"))
        try:
            read_recording(path)
        except DataError as exc:
            message = str(exc)
            assert "\n" not in message and str(path) in message


# --------------------------------------------------------------------------- problem files
WEIRD = [
    1e308, -1e308, -0.0, 0.0, 0, -1, 1, 10**30, -(10**30), 2**64, 1e-320, 0.5, "nan", ".nan",
    "inf", "", " ", "x", "1e3", None, True, False, [], {}, [1, 2], {"a": 1}, "mumps", "ma27",
    "exact", "fourier", "reduced_rank",
]  # fmt: skip
IPOPT_OPTIONS = [
    "tol", "max_iter", "mu_strategy", "acceptable_tol", "linear_solver", "print_level",
    "hessian_approximation", "bogus_option", "mumps_pivot_order", "output_file",
]  # fmt: skip


def _paths(data, prefix=()):
    """Every key path of a nested mapping (list items by index)."""
    out = []
    items = (
        data.items()
        if isinstance(data, dict)
        else enumerate(data)
        if isinstance(data, list)
        else ()
    )
    for key, value in items:
        out.append((*prefix, key))
        out.extend(_paths(value, (*prefix, key)))
    return out


def _container(data, path):
    node = data
    for key in path[:-1]:
        node = node[key]
    return node


@st.composite
def mutated(draw: st.DrawFn, base: dict) -> dict:
    """The problem with a few keys removed, values replaced by wrong types or extreme numbers,
    unknown keys added or IPOPT options set."""
    data = copy.deepcopy(base)
    for _ in range(draw(st.integers(min_value=1, max_value=3))):
        paths = _paths(data)
        kind = draw(st.sampled_from(["remove", "replace", "replace", "add", "ipopt"]))
        if kind in ("remove", "replace") and paths:
            path = draw(st.sampled_from(paths))
            node = _container(data, path)
            if kind == "remove" and isinstance(node, dict):
                del node[path[-1]]
            else:
                node[path[-1]] = copy.deepcopy(draw(st.sampled_from(WEIRD)))
        elif kind == "add":
            dicts = [(), *(p for p in paths if isinstance(_container(data, (*p, 0)), dict))]
            where = draw(st.sampled_from(dicts))
            node = _container(data, (*where, 0))
            node[draw(st.sampled_from(["extra", "seed", "model", "solver", "x"]))] = copy.deepcopy(
                draw(st.sampled_from(WEIRD))
            )
        elif kind == "ipopt":
            solver = data.setdefault("solver", {})
            if isinstance(solver, dict):
                options = solver.setdefault("ipopt", {})
                if isinstance(options, dict):
                    options[draw(st.sampled_from(IPOPT_OPTIONS))] = copy.deepcopy(
                        draw(st.sampled_from(WEIRD))
                    )
    return data


def _dump(data) -> str:
    buf = io.StringIO()
    yaml.safe_dump(data, buf, sort_keys=False)
    return buf.getvalue()


def _check(load, data, tmp: Path, names_file: bool = True):
    path = tmp / "p.yaml"
    path.write_text(_dump(data))
    try:
        load(path)
    except ProblemError as exc:
        assert "\n" not in str(exc)
        assert not names_file or str(exc).startswith(str(path)), str(exc)


def _base(name):
    return yaml.safe_load((ROOT / name).read_text())


@pytest.mark.parametrize(
    "name", ["problems/paper/base.yaml", "problems/bench/walk.yaml"], ids=["base", "walk"]
)
def test_a_mutated_problem_file_loads_or_is_one_problem_error(name):
    @SETTINGS
    @given(data=mutated(_base(name)))
    def check(data):
        with tempfile.TemporaryDirectory() as folder:
            _check(load_problem, data, Path(folder))

    check()


def test_a_mutated_imu_problem_file_loads_or_is_one_problem_error():
    @SETTINGS
    @given(data=mutated(_base("problems/imu/rectangle.yaml")))
    def check(data):
        with tempfile.TemporaryDirectory() as folder:
            _check(load_imu_problem, data, Path(folder))

    check()


def test_a_mutated_planar_problem_file_loads_or_is_one_problem_error():
    base = {
        "model": {"sigma_disp": 0.01, "sigma_m": 0.01, "num_basis": 64},
        "solver": {"tol": 1e-5},
    }

    @SETTINGS
    @given(data=mutated(base))
    def check(data):
        with tempfile.TemporaryDirectory() as folder:
            _check(load_planar_options, data, Path(folder))

    check()


def test_a_mutated_table_file_plans_or_is_one_problem_error():
    table = _base("problems/paper/table1.yaml")
    table["problem"] = str(ROOT / "problems/paper" / table["problem"])

    @settings(SETTINGS, max_examples=60)
    @given(data=mutated(table))
    def check(data):
        with tempfile.TemporaryDirectory() as folder:
            load = lambda p: load_sweep(p, Path(folder) / "out", seeds=1)  # noqa: E731
            _check(load, data, Path(folder), names_file=False)

    check()


@SETTINGS
@given(
    text=st.text(
        alphabet=st.sampled_from([*"seed: 1\n  {}[]-#&*!|>'\"%@`,?x0.e", "\t", "\u00a0"]),
        max_size=60,
    )
)
def test_any_problem_text_loads_or_is_one_problem_error(text):
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "p.yaml"
        path.write_text(text)
        try:
            load_problem(path)
        except ProblemError as exc:
            assert "\n" not in str(exc) and str(path) in str(exc)


@SETTINGS
@given(
    key=st.sampled_from(["seed", "model.gp.sigma_f", "solver.ipopt.tol", "simulation", "a..b", ""]),
    value=st.sampled_from(["1", "1e308", "-0.0", ".nan", "", "{a: 1, a: 2}", "[", "'", "x", "1_0"]),
)
def test_any_override_applies_or_is_one_problem_error(key, value):
    try:
        load_problem({"seed": 1}, f"{key}={value}")
    except ProblemError as exc:
        assert "\n" not in str(exc)
