"""DH/Hayati reporting reproduces data-sheet geometry and reacts to calibrated errors."""
import numpy as np
import pytest

from kpi_calib_ros.core.model.dh import describe, dh_table
from kpi_calib_ros.core.model.robot_library import kr15_class


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


@pytest.mark.parametrize('tilt', [0.005, 0.02, 0.05])
def test_nearly_parallel_axes_2_3_are_hayati_never_metres_of_d(cm, tilt):
    # A tilt of axis 3 towards the upper arm: DH would put the common normal
    # a2 / tan(tilt) away (34 m at 0.02 rad), an artefact of the convention.
    p = cm.geometric.with_values({'joint_3.placement.rx': tilt})
    rows = describe(cm.robot, cm.geometric, p)
    assert [r.convention for r in rows] == ['DH', 'Hayati', 'DH', 'DH', 'DH']
    assert max(abs(r.d) for r in rows) < 1.0
    assert abs(rows[1].beta) == pytest.approx(tilt, abs=1e-12)
    assert rows[1].alpha == pytest.approx(0.0, abs=1e-12)
    assert rows[1].a == pytest.approx(kr15_class().a2, abs=1e-12)
    # The next DH row is measured from the Hayati origin on axis 3: unchanged d.
    nominal = describe(cm.robot, cm.geometric, cm.geometric.nominal)
    assert rows[2].d == pytest.approx(nominal[2].d, abs=1e-9)


def test_hayati_keeps_both_twists_and_the_nominal_convention(cm):
    p = cm.geometric.with_values({'joint_3.placement.rz': 0.02})   # twist about the upper arm
    # On its own the twisted pair has a proper common normal (DH, alpha = 20 mrad)...
    assert describe(cm.robot, cm.geometric, p)[1].convention == 'DH'
    # ...but beside its nominal it stays Hayati, the twist in alpha.
    row = dh_table(cm.robot, cm.geometric, cm.geometric.nominal, p)[1]
    assert row['convention'] == 'Hayati' and set(row['calibrated']) == {'theta', 'a', 'alpha',
                                                                        'beta'}
    assert abs(row['calibrated']['alpha']) == pytest.approx(0.02, abs=1e-12)
    assert row['calibrated']['beta'] == pytest.approx(0.0, abs=1e-12)
    both = describe(cm.robot, cm.geometric,
                    cm.geometric.with_values({'joint_3.placement.rx': 0.003,
                                              'joint_3.placement.rz': 0.004}))[1]
    # Small rotations compose to first order: each twist to within 3e-3 * 4e-3.
    assert abs(both.alpha) == pytest.approx(0.004, abs=2e-5)
    assert abs(both.beta) == pytest.approx(0.003, abs=2e-5)
