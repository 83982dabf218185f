"""DH/Hayati reporting reproduces data-sheet geometry and reacts to calibrated errors."""
import numpy as np
import pytest

from kpi_calib_ros.core.dh import describe, dh_table
from kpi_calib_ros.core.robot_library import kr15_class
from kpi_calib_ros.io.cell import DEFAULT_CELL, build_cell_model, load_cell


@pytest.fixture(scope='module')
def cm():
    return build_cell_model(load_cell(DEFAULT_CELL))


def test_nominal_kr15_dh_equals_data_sheet(cm):
    g = kr15_class()
    rows = describe(cm.robot, cm.geometric, cm.geometric.nominal)
    assert [r.convention for r in rows] == ['DH', 'Hayati', 'DH', 'DH', 'DH']
    assert abs(rows[0].d) == pytest.approx(g.d1) and abs(rows[0].a) == pytest.approx(g.a1)
    assert rows[1].a == pytest.approx(g.a2) and rows[1].beta == pytest.approx(0.0)
    assert abs(rows[2].a) == pytest.approx(g.a3)
    assert abs(rows[3].d) == pytest.approx(g.d4)
    assert [abs(r.alpha) for r in rows if r.convention == 'DH'] == pytest.approx([np.pi / 2] * 4)


def test_calibrated_errors_show_in_the_table(cm):
    p = cm.geometric.with_values({'joint_3.placement.tz': 0.0005,    # upper arm 0.5 mm longer
                                  'joint_3.placement.rx': 0.001})   # axes 2/3 tilted 1 mrad
    rows = dh_table(cm.robot, cm.geometric, cm.geometric.nominal, p)
    hayati = rows[1]
    assert hayati['convention'] == 'Hayati'
    assert hayati['calibrated']['a'] - hayati['nominal']['a'] == pytest.approx(0.0005, abs=1e-9)
    assert abs(hayati['calibrated']['beta']) == pytest.approx(0.001, abs=1e-9)
