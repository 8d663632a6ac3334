"""The paper's published numbers (Chow 2017, Section 3.1, Tables 1-5), one run per row.

Every value is a position error in metres as printed in the paper: RMSE and maximum error of
the odometry-only trajectory ("Before SLAM") and of the GP-SLAM estimate ("After SLAM").
Tables 1-4 share one "Before SLAM" row; Table 5 prints one per odometry noise level.
Table 6 (recovered IMU biases, a real recording) has no simulated counterpart here.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class PaperRow:
    """One "After SLAM" row of a paper table.

    key: short identifier used by the table files in ``problems/paper/`` (``sigma_f=0.001``);
    label: the row's text in the paper's layout; rmse_before, max_before, rmse_after,
    max_after: the published errors [m].
    """

    key: str
    label: str
    rmse_before: float
    max_before: float
    rmse_after: float
    max_after: float

    @property
    def improved(self) -> bool:
        """Whether the paper's GP-SLAM improved on odometry in this row (RMSE after < before)."""
        return self.rmse_after < self.rmse_before


@dataclass(frozen=True)
class PaperTable:
    """A table of the paper: its number, caption, what the rows vary, and the rows."""

    id: str
    number: int
    caption: str
    varies: str
    rows: tuple[PaperRow, ...]

    def row(self, key: str) -> PaperRow:
        for r in self.rows:
            if r.key == key:
                return r
        raise KeyError(key)

    @property
    def keys(self) -> tuple[str, ...]:
        return tuple(r.key for r in self.rows)


# Section 3.1: "Before SLAM" of Tables 1-4 (bias 5 mm in X and Y, odometry noise 0.5 mm).
_BEFORE = (0.066, 0.112)


def _rows(before: tuple[float, float], rows: list[tuple[str, str, float, float]]) -> tuple:
    return tuple(PaperRow(k, label, *before, rmse, mx) for k, label, rmse, mx in rows)


TABLES: dict[str, PaperTable] = {
    "table1": PaperTable(
        id="table1",
        number=1,
        caption="Error in estimated trajectory for various sigma_f",
        varies="true sigma_f (model at truth)",
        rows=_rows(
            _BEFORE,
            [
                ("sigma_f=0.001", "sigma_f = 0.001", 0.189, 0.318),
                ("sigma_f=0.100", "sigma_f = 0.100", 0.003, 0.005),
                ("sigma_f=1.000", "sigma_f = 1.000", 0.004, 0.006),
                ("sigma_f=10.00", "sigma_f = 10.00", 0.003, 0.005),
            ],
        ),
    ),
    "table2": PaperTable(
        id="table2",
        number=2,
        caption="Error in estimated trajectory when using the wrong sigma_f",
        varies="assumed sigma_f (true sigma_f = 0.1)",
        rows=_rows(
            _BEFORE,
            [
                ("sigma_f=0.001", "sigma_f = 0.001", 0.206, 0.346),
                ("sigma_f=0.010", "sigma_f = 0.010", 0.103, 0.174),
                ("sigma_f=1.000", "sigma_f = 1.000", 0.004, 0.006),
                ("sigma_f=10.00", "sigma_f = 10.00", 0.004, 0.006),
            ],
        ),
    ),
    "table3": PaperTable(
        id="table3",
        number=3,
        caption="Error in estimated trajectory for various l",
        varies="true l (model at truth)",
        rows=_rows(
            _BEFORE,
            [
                ("l=0.1", "l = 0.1m", 0.003, 0.005),
                ("l=0.4", "l = 0.4m", 0.012, 0.021),
            ],
        ),
    ),
    "table4": PaperTable(
        id="table4",
        number=4,
        caption="Error in estimated trajectory when using the wrong l",
        varies="assumed l (true l = 0.1 m)",
        rows=_rows(
            _BEFORE,
            [
                ("l=0.005", "l = 0.005m", 0.003, 0.004),
                ("l=0.050", "l = 0.050m", 0.003, 0.005),
                ("l=0.150", "l = 0.150m", 0.004, 0.006),
                ("l=0.400", "l = 0.400m", 0.127, 0.214),
            ],
        ),
    ),
    "table5": PaperTable(
        id="table5",
        number=5,
        caption=(
            "Errors in estimated trajectory when varying the odometry noise. "
            "The bias in X and Y are set to 15mm and l is 0.4m"
        ),
        varies="odometry noise (bias 15 mm, true l = 0.4 m)",
        rows=(
            PaperRow("noise=0.5mm", "Odometry noise = 0.5mm", 0.191, 0.328, 0.012, 0.021),
            PaperRow("noise=2.5mm", "Odometry noise = 2.5mm", 0.196, 0.334, 0.012, 0.024),
            PaperRow("noise=5.0mm", "Odometry noise = 5.0mm", 0.201, 0.338, 0.154, 0.222),
        ),
    ),
}


def paper_table(table_id: str) -> PaperTable:
    """The paper's table by id (``table1`` ... ``table5``); KeyError names the known ids."""
    try:
        return TABLES[table_id]
    except KeyError:
        raise KeyError(f"{table_id!r} is not a table of the paper ({', '.join(TABLES)})") from None
