"""learned_residual.yaml read back: the tool reads every file it writes, and a hostile file is
a named error, never a crash or a stall.

The covariances identify computes are symmetric only to rounding (~1e-11 of their scale), in
entries near zero far more than their own size; they are written symmetrised and read with a
tolerance relative to their diagonal. A kernel that cannot be factored, a training set above
MAX_TRAINING_ROWS, a file above the byte or item bound and non-finite numbers are ConfigErrors
naming the file and the field; ``kpi-calib validate`` exits 2 with that message, and with
``--register`` (which carries the field into the registered set-up) refuses it the same
way."""
from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from kpi_calib_ros.cli import main
from kpi_calib_ros.core.diagnosis.learned_residual import (
    MAX_TRAINING_ROWS,
    LearnedResidual,
    SingularKernelError,
    fit_learned_residual,
)
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.io.cell import DEFAULT_CELL
from kpi_calib_ros.io.learned_residual_file import (
    MAX_FILE_BYTES,
    MAX_FILE_ITEMS,
    read_residual,
    residual_document,
    write_residual,
)
from kpi_calib_ros.io.yaml_bounded import indicator_count, load_yaml_bounded

JOINTS = tuple(f'joint_{i}' for i in range(1, 7))
K = 12  # estimated parameters


def fitted(seed: int = 0, rows: int = 60):
    """A fitted learned residual of a smooth map of two joints, 20 µm noise."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-2.0, 2.0, (rows, 6))
    y = 5e-5 * np.column_stack([np.sin(q[:, 1]), np.cos(q[:, 2]), np.sin(q[:, 1] + q[:, 2])])
    return fit_learned_residual(q, y + rng.normal(0, 2e-5, y.shape), 2e-5, JOINTS, seed=seed)


def rounded_covariance(seed: int = 1) -> np.ndarray:
    """A (K, K) covariance as identify's arithmetic leaves it: two groups of parameters the
    measurements do not couple (entries ~1e-30 of their scale) and an asymmetry of ~1e-11
    of sqrt(C_ii C_jj) everywhere, far larger than the near-zero entries themselves."""
    rng = np.random.default_rng(seed)
    cov = np.zeros((K, K))
    for block in (slice(0, 6), slice(6, K)):
        a = rng.normal(size=(6, 6)) * 1e-5
        cov[block, block] = a @ a.T + 1e-12 * np.eye(6)
    scale = np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    return cov + 1e-11 * scale * rng.uniform(-1, 1, (K, K))


def document(choice, covariance: np.ndarray) -> dict:
    names = tuple(f'p{i}' for i in range(K))
    result = SimpleNamespace(names=names, values=np.linspace(0, 1, K), estimated=names)
    return residual_document(choice, result, covariance, covariance, ())


@pytest.fixture(scope='module')
def choice():
    return fitted()


def test_a_covariance_symmetric_to_rounding_is_written_symmetric_and_read_back(choice,
                                                                                 tmp_path):
    cov = rounded_covariance()
    assert not np.allclose(cov, cov.T, rtol=1e-9, atol=0)  # entrywise it is not symmetric
    stored = read_residual(write_residual(tmp_path, document(choice, cov)))
    written = np.array(yaml.safe_load((tmp_path / 'learned_residual.yaml').read_text())
                       ['physical']['covariance'])
    np.testing.assert_array_equal(written, written.T)
    np.testing.assert_array_equal(stored.covariance, 0.5 * (cov + cov.T))
    # A file written before identify symmetrised (the same numbers, unsymmetrised) reads too,
    # and comes back symmetric.
    doc = document(choice, cov)
    doc['physical']['covariance'] = cov.tolist()
    stored = read_residual(write_residual(tmp_path, doc))
    np.testing.assert_array_equal(stored.covariance, stored.covariance.T)
    np.testing.assert_allclose(stored.covariance, cov, rtol=0, atol=1e-10 * np.abs(cov).max())
    # An asymmetry beyond rounding is refused by name.
    doc['physical']['covariance'][0][1] *= 1.001
    with pytest.raises(ConfigError, match=r'physical\.covariance.*must be symmetric'):
        read_residual(write_residual(tmp_path, doc))


def test_a_kernel_that_cannot_be_factored_is_refused(choice, tmp_path):
    """An amplitude beyond what identify fits (here 1e10 m²: in floating point the kernel
    matrix of repeated poses is rank one) is refused by its field; the kernel matrix is
    factored once, and one that is not positive definite is a SingularKernelError."""
    model = choice.model
    doc = document(choice, rounded_covariance())
    doc['kernel']['amplitude_m2'] = 1e10
    doc['training']['q'] = [list(doc['training']['q'][0]) for _ in doc['training']['q']]
    path = write_residual(tmp_path, doc)
    with pytest.raises(ConfigError, match=r'kernel\.amplitude_m2.*learned_residual\.yaml.*'
                                          r'must be at most 0\.01'):
        read_residual(path)
    with pytest.raises(SingularKernelError, match='not positive definite'):
        LearnedResidual(JOINTS, np.repeat(model.q[:1], 40, axis=0), model.residual_m[:40],
                        1e10, model.length_scales, model.noise_m2)


def test_a_training_set_above_the_bound_is_refused_by_name(choice, tmp_path):
    rows = MAX_TRAINING_ROWS + 1
    path = tmp_path / 'learned_residual.yaml'
    path.write_text(dumped(repeated(document(choice, rounded_covariance()), rows)))
    assert path.stat().st_size < MAX_FILE_BYTES
    with pytest.raises(ConfigError, match=rf'training\.q.*{path}.*has {rows} rows, more than '
                                          rf'the {MAX_TRAINING_ROWS}'):
        read_residual(path)


@pytest.mark.slow
def test_a_file_above_the_byte_or_item_bound_is_refused_before_it_is_parsed(choice,
                                                                            tmp_path):
    """60 000 training rows as identify would write them: refused by size at once (they
    took 70 s to parse and a 26.8 GiB kernel matrix to fail). Rows of two-byte numbers
    under the byte bound: refused by their number of items, before parsing."""
    path = tmp_path / 'learned_residual.yaml'
    path.write_text(dumped(repeated(document(choice, rounded_covariance()), 60_000)))
    assert path.stat().st_size > MAX_FILE_BYTES
    start = time.perf_counter()
    with pytest.raises(ConfigError, match=rf'{path} is \d+ bytes, more than the '
                                          rf'{MAX_FILE_BYTES} bytes'):
        read_residual(path)
    print(f'{path.stat().st_size} bytes refused in {time.perf_counter() - start:.3f} s')
    compact = 'training:\n q:\n' + ' - [0,0,0,0,0,0]\n' * (MAX_FILE_BYTES // 20)
    path.write_text(compact)
    assert indicator_count(compact) > MAX_FILE_ITEMS and len(compact) < MAX_FILE_BYTES
    start = time.perf_counter()
    with pytest.raises(ConfigError, match=rf'{path} has \d+ YAML items .* more than the '
                                          rf'{MAX_FILE_ITEMS}'):
        read_residual(path)
    print(f'{len(compact)} bytes of compact rows refused in {time.perf_counter() - start:.3f} s')


@pytest.mark.parametrize('text', [
    'a: [1, {b: c, d: [e, f]}]\nlist:\n  - - 1\n    - -2.0e-05\n  -\n  - ? k\n    : v\n',
    'a: &x [1, 2]\nb: *x\n', '[[[[0]]]]', 'a', '', '{a: b, c: d}', '- |\n  text: [x]\n- "q: ,"\n'])
def test_the_item_count_bounds_the_nodes(text):
    """Every node but the root is introduced by an indicator: twice their count bounds the
    nodes of any document, whatever its style."""
    nodes = 0
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return
    seen: set[int] = set()
    stack = [root] if root is not None else []
    while stack:
        node = stack.pop()
        if id(node) in seen:
            continue
        seen.add(id(node))
        nodes += 1
        if isinstance(node, yaml.SequenceNode):
            stack.extend(node.value)
        elif isinstance(node, yaml.MappingNode):
            stack.extend(n for pair in node.value for n in pair)
    assert nodes <= 2 * indicator_count(text) + 1, (text, nodes)
    load_yaml_bounded(text, 'x', 'k', 'fix', max_items=indicator_count(text))


def test_non_finite_numbers_are_refused_by_name(choice, tmp_path):
    doc = document(choice, rounded_covariance())
    doc['training']['q'][7][2] = float('inf')
    with pytest.raises(ConfigError, match=r'training\.q\[7\]\[2\].*must be a finite number'):
        read_residual(write_residual(tmp_path, doc))
    doc = document(choice, rounded_covariance())
    doc['physical']['covariance_outside'][3][3] = float('nan')
    with pytest.raises(ConfigError, match=r'physical\.covariance_outside\[3\]\[3\]'):
        read_residual(write_residual(tmp_path, doc))


@pytest.fixture(scope='module')
def calibrated(tmp_path_factory):
    """A calibration.yaml of the built-in cell (no learned residual) and a new recording."""
    tmp = tmp_path_factory.mktemp('calibrated')
    for name, seed in (('train', 1), ('new', 2)):
        assert main(['simulate', '--cell', str(DEFAULT_CELL), '--n', '40', '--out',
                     str(tmp / f'{name}.mcap'), '--seed', str(seed)]) == 0
    assert main(['identify', '--cell', str(DEFAULT_CELL), '--bag', str(tmp / 'train.mcap'),
                 '--out', str(tmp / 'out'), '--model', 'geometric']) == 0
    return tmp


def dumped(doc: dict) -> str:
    """``doc`` as write_residual writes it, by libyaml's emitter (large documents)."""
    return yaml.dump(doc, Dumper=yaml.CSafeDumper, sort_keys=False)


def repeated(doc: dict, rows: int) -> dict:
    """``doc`` with its training rows repeated to ``rows`` (copies: no YAML alias)."""
    for key in ('q', 'residual_m'):
        given = doc['training'][key]
        doc['training'][key] = [list(given[i % len(given)]) for i in range(rows)]
    return doc


def hostile_files(choice) -> dict[str, tuple[dict, str]]:
    """learned_residual.yaml documents that must be refused, with the field named."""
    out: dict[str, tuple[dict, str]] = {}
    doc = document(choice, rounded_covariance())
    doc['kernel']['amplitude_m2'] = 1e10
    doc['training']['q'] = [list(doc['training']['q'][0]) for _ in doc['training']['q']]
    out['singular kernel'] = (doc, 'kernel.amplitude_m2')
    out['oversize training set'] = (repeated(document(choice, rounded_covariance()),
                                             MAX_TRAINING_ROWS + 1), 'training.q')
    out['60 000 rows'] = (repeated(document(choice, rounded_covariance()), 60_000),
                          'bytes, more than')
    doc = document(choice, rounded_covariance())
    doc['training']['residual_m'][5][0] = float('nan')
    out['non-finite'] = (doc, 'training.residual_m[5][0]')
    return out


@pytest.mark.slow
def test_validate_exits_2_naming_a_hostile_file_with_and_without_register(
        calibrated, choice, capsys):
    out = calibrated / 'out'
    args = ['validate', '--cell', str(DEFAULT_CELL), '--calibration',
            str(out / 'calibration.yaml'), '--bag', str(calibrated / 'new.mcap')]
    path = out / 'learned_residual.yaml'
    try:
        for name, (doc, field) in hostile_files(choice).items():
            path.write_text(dumped(doc))
            capsys.readouterr()
            assert main(args + ['--out', str(calibrated / 'val')]) == 2, name
            err = capsys.readouterr().err
            assert str(path) in err and field in err, (name, err)
            assert 'Traceback' not in err
            # --register carries the learned residual into the registered set-up: it is
            # read there too, and refused the same way.
            assert main(args + ['--out', str(calibrated / 'val_reg'), '--register']) == 2, name
            err = capsys.readouterr().err
            assert str(path) in err and field in err and 'Traceback' not in err, (name, err)
    finally:
        path.unlink(missing_ok=True)
