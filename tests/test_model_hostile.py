"""Hostile model files.

Every one ends in ModelFileError, quickly, or in a model that says whether it can be trusted.
"""

from __future__ import annotations

import json
import time
import zipfile

import _hostile as h
import numpy as np
import pytest

from soft_rom import models
from soft_rom.errors import ModelFileError
from soft_rom.models import DiscreteModel, load_model, SecondOrderModel

MAX_STATES = getattr(models, 'MAX_STATES', 256)


def _refused(path, match: str | None = None) -> str:
    t0 = time.perf_counter()
    with pytest.raises(ModelFileError, match=match) as info:
        load_model(path)
    assert time.perf_counter() - t0 < 2.0
    assert '\n' not in str(info.value)
    return str(info.value)


def test_deeply_nested_json(tmp_path) -> None:
    _refused(h.with_metadata_text(h.second_order(), tmp_path / 'm.npz', '[' * 100_000),
             'nested|JSON')
    header = h.second_order().header()
    deep: object = {}
    for _ in range(60):
        deep = {'a': deep}
    header['metadata'] = deep
    _refused(h.with_metadata_text(h.second_order(), tmp_path / 'm2.npz', json.dumps(header)),
             'nested')


def test_huge_integer_in_json(tmp_path) -> None:
    model = h.second_order()
    text = json.dumps(model.header()).replace('"r": 3', '"r": ' + '7' * 5000)
    _refused(h.with_metadata_text(model, tmp_path / 'm.npz', text), 'digits|JSON')


def test_nan_infinity_and_surrogates_in_json(tmp_path) -> None:
    model = h.second_order()
    text = json.dumps(model.header()).replace('"note": "ok"', '"note": NaN')
    _refused(h.with_metadata_text(model, tmp_path / 'nan.npz', text), 'NaN')
    text = json.dumps(model.header()).replace('"note": "ok"', '"note": 1e999')
    _refused(h.with_metadata_text(model, tmp_path / 'inf.npz', text), 'range')
    text = json.dumps(model.header()).replace('"note": "ok"', '"note": "\\ud800"')
    _refused(h.with_metadata_text(model, tmp_path / 'sur.npz', text), 'surrogate|encode')
    _refused(h.with_header(model, tmp_path / 'ctl.npz', output_names=['a\x1b[2J', 'b', 'c', 'd']),
             'printable')


def test_member_without_numpy_magic(tmp_path) -> None:
    model = h.second_order()
    _refused(h.with_arrays(model, tmp_path / 'm.npz', K=b'just some bytes, not npy'), 'magic')
    members = h.members_of(model)
    members['__metadata__.npy'] = json.dumps(model.header()).encode()
    _refused(h.write_zip(tmp_path / 'm2.npz', members), 'magic')


@pytest.mark.parametrize('method', [99, 14, 12])
def test_unknown_compression_method(tmp_path, method) -> None:
    path = h.patch_zip_fields(h.write_zip(tmp_path / 'm.npz', h.members_of(h.second_order())),
                              method=method)
    _refused(path, 'compression method')


def test_encrypted_flag(tmp_path) -> None:
    path = h.patch_zip_fields(h.write_zip(tmp_path / 'm.npz', h.members_of(h.second_order())),
                              flags=0x1)
    _refused(path, 'encrypted')


def test_corrupt_deflate_stream(tmp_path) -> None:
    _refused(h.corrupt_deflate(h.second_order(), tmp_path / 'm.npz'), 'corrupt')


def test_deflated_archive_of_a_valid_model_loads(tmp_path) -> None:
    model = h.second_order()
    path = h.write_zip(tmp_path / 'm.npz', h.members_of(model),
                       compression=zipfile.ZIP_DEFLATED)
    loaded = load_model(path)
    assert np.array_equal(loaded.K, model.K) and loaded.trusted


@pytest.mark.parametrize('header', [
    "{'descr': '<f8', 'fortran_order': False, 'shape': (3, 3), '''",    # tokenize error
    "{'descr': '<f8', 'fortran_order': False, 'shape': (3, 3)" + ' (' * 1500,
    "{'descr': '<f8', 'fortran_order': False, 'shape': (3, 3), 'x': 1}",
    "{'descr': 'O', 'fortran_order': False, 'shape': (3, 3), }",
    "{'descr': '<i8', 'fortran_order': False, 'shape': (3, 3), }",
    "{'descr': '<f8', 'fortran_order': 0, 'shape': (3, 3), }",
    "{'descr': '<f8', 'fortran_order': False, 'shape': (3, -3), }",
    "{'descr': '<f8', 'fortran_order': False, 'shape': (3, 3.0), }",
    "__import__('os').system('touch /tmp/soft_rom_pwned')",
])
def test_npy_header_is_parsed_not_evaluated(tmp_path, header) -> None:
    bad = h.npy_raw(header + ' ' * 8 + '\n', bytes(72))
    _refused(h.with_arrays(h.second_order(), tmp_path / 'm.npz', K=bad))


def test_declared_shape_larger_than_the_entry(tmp_path) -> None:
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': (1000000, 1000000), }"
    bad = h.npy_raw(header + '    \n', bytes(72))   # 7.28 TiB declared, 72 bytes present
    msg = _refused(h.with_arrays(h.second_order(), tmp_path / 'm.npz', K=bad), 'declares')
    assert '1000000' in msg


def test_declared_uncompressed_size_checked_before_reading(tmp_path) -> None:
    path = h.write_zip(tmp_path / 'm.npz', h.members_of(h.second_order()),
                       compression=zipfile.ZIP_DEFLATED)
    h.declare_size(path, 'K.npy', 12_500 * 12_500 * 8)
    _refused(path, 'MiB')


def test_unknown_entry_refused_from_the_directory(tmp_path) -> None:
    members = h.members_of(h.second_order())
    members['evil.npy'] = h.npy_bytes(np.zeros(10))
    path = h.write_zip(tmp_path / 'm.npz', members, compression=zipfile.ZIP_DEFLATED)
    h.declare_size(path, 'evil.npy', 2_000_000_000)
    _refused(path, 'unexpected archive entry')
    members = h.members_of(h.second_order())
    members['notes.txt'] = b'hello'
    _refused(h.write_zip(tmp_path / 'm2.npz', members), 'unexpected')


def test_multi_disk_zip64_record(tmp_path) -> None:
    _refused(h.multi_disk_zip64(tmp_path / 'm.npz'), 'corrupt')


@pytest.mark.parametrize('change, match', [
    ({'dt': 1e300}, 'dt'), ({'dt': -1.0}, 'dt'), ({'dt': 0}, 'dt'), ({'dt': 'x'}, 'dt'),
    ({'dt': True}, 'dt'), ({'r': 0}, 'r'), ({'r': 7}, 'r=7'), ({'n_states': 2}, 'n_states'),
    ({'method': 'x' * 100}, 'method'), ({'class': 'Nope'}, 'class'),
    ({'input_names': ['a']}, 'names'), ({'metadata': [1, 2]}, 'metadata'),
    ({'format_version': '1'}, 'must be an integer'), ({'format_version': 1.0}, 'integer'),
    ({'format_version': True}, 'integer'), ({'format_version': 99}, 'version 99'),
])
def test_physical_fields(tmp_path, change, match) -> None:
    _refused(h.with_header(h.second_order(), tmp_path / 'm.npz', **change), match)


def test_a_file_whose_method_contradicts_its_class_is_refused(tmp_path) -> None:
    """A SecondOrderModel file saying method 'era' loaded as an LOpInf model, silently."""
    model = h.second_order()
    _refused(h.with_header(model, tmp_path / 'era.npz', method='era'),
             r"SecondOrderModel cannot have method 'era' \(its method is 'lopinf'\)")
    assert load_model(h.with_header(model, tmp_path / 'ok.npz', method='lopinf')).method == \
        'lopinf'
    members = h.members_of(model)           # no method declared: the class's own
    members['__metadata__.npy'] = h.npy_bytes(h.meta_array(
        {k: v for k, v in model.header().items() if k != 'method'}))
    assert isinstance(load_model(h.write_zip(tmp_path / 'none.npz', members)), SecondOrderModel)
    era = h.discrete()                      # a DiscreteModel keeps any declared method
    assert load_model(era.save(tmp_path / 'd.npz')).method == 'era'


def test_magnitudes_and_empty_shapes(tmp_path) -> None:
    model = h.second_order()
    _refused(h.with_arrays(model, tmp_path / 'k.npz', K=model.K * 1e300), 'magnitude')
    _refused(h.with_arrays(model, tmp_path / 'y.npz', y_ref=np.full(4, 1e300)), 'magnitude')
    _refused(h.write_zip(tmp_path / 'r0.npz', {
                 **h.members_of(model), 'K.npy': h.npy_bytes(np.zeros((0, 0))),
                 'C.npy': h.npy_bytes(np.zeros((0, 0))), 'B.npy': h.npy_bytes(np.zeros((0, 2))),
                 'E.npy': h.npy_bytes(np.zeros((4, 0)))}), 'states|r=')


def test_stiff_model_that_overflows_is_refused(tmp_path) -> None:
    model = h.second_order()
    # entries are plausible numbers but the system explodes over one step
    K = -np.eye(3) * 1e140
    _refused(h.with_arrays(model, tmp_path / 'k.npz', K=K, C=np.zeros((3, 3))),
             'overflow|exponential|not finite')


def test_too_many_states_refused_before_any_algebra(tmp_path) -> None:
    r = MAX_STATES // 2 + 1
    model = SecondOrderModel(np.eye(r), np.eye(r), np.ones((r, 1)), np.ones((1, r)), dt=1e-3)
    members = {f'{k}.npy': h.npy_bytes(v) for k, v in model.matrices().items()}
    members['y_ref.npy'] = h.npy_bytes(model.y_ref)
    header = {**h.second_order().header(), 'r': r, 'n_states': 2 * r,
              'input_names': None, 'output_names': None, 'input_units': None,
              'output_units': None}
    members['__metadata__.npy'] = h.npy_bytes(h.meta_array(header))
    t0 = time.perf_counter()
    _refused(h.write_zip(tmp_path / 'm.npz', members, compression=zipfile.ZIP_DEFLATED),
             'states')
    assert time.perf_counter() - t0 < 1.0
    with pytest.raises(ModelFileError, match='states'):
        model.save(tmp_path / 'big.npz')


def test_directory_and_unreadable_file(tmp_path) -> None:
    (tmp_path / 'd.npz').mkdir()
    _refused(tmp_path / 'd.npz', 'regular file')
    with pytest.raises(FileNotFoundError):
        load_model(tmp_path / 'missing.npz')


# -- trust ------------------------------------------------------------------------------

def test_trusted_models_say_so(tmp_path) -> None:
    for model in (h.second_order(), h.discrete()):
        loaded = load_model(model.save(tmp_path / f'{model.method}.npz'), strict=True)
        assert loaded.trusted and loaded.trust_issues() == []


def test_unstable_discrete_model_is_not_trusted(tmp_path) -> None:
    path = h.discrete(radius=1.5).save(tmp_path / 'm.npz')
    model = load_model(path)
    issues = model.trust_issues()
    assert len(issues) == 1 and 'spectral radius' in issues[0] and '1.5' in issues[0]
    with pytest.raises(ModelFileError, match='cannot be trusted.*spectral radius'):
        load_model(path, strict=True)


def test_marginal_model_is_trusted() -> None:
    integrator = DiscreteModel(np.eye(2), np.ones((2, 1)), np.ones((1, 2)), dt=0.1)
    assert integrator.trusted


@pytest.mark.parametrize('which, sign, match', [
    ('K', -1.0, 'K is negative definite'), ('C', -1.0, 'C is negative definite'),
    ('K', 0.0, 'K is indefinite'),
])
def test_indefinite_stiffness_or_damping(tmp_path, which, sign, match) -> None:
    model = h.second_order()
    M = getattr(model, which).copy()
    if sign == 0.0:
        M = np.diag([5.0, -1.0, 3.0])
    else:
        M = sign * M
    path = h.with_arrays(model, tmp_path / 'm.npz', **{which: M})
    loaded = load_model(path)
    assert any(match in i for i in loaded.trust_issues()), loaded.trust_issues()
    assert any(i.startswith('unstable') for i in loaded.trust_issues())
    with pytest.raises(ModelFileError, match='cannot be trusted'):
        load_model(path, strict=True)


def test_absurd_offsets_are_not_trusted(tmp_path) -> None:
    model = h.second_order()
    loaded = load_model(h.with_arrays(model, tmp_path / 'm.npz', y_ref=np.full(4, 3e7)))
    assert loaded.trust_issues() == ['absurd output offset: max |y_ref| = 3e+07']


def test_registered_model_class_with_an_extra_tensor(tmp_path) -> None:
    register_model_class = models.register_model_class

    @register_model_class
    class TensorModel(SecondOrderModel):
        _matrix_names = ('K', 'C', 'B', 'E', 'G')
        _file_methods = ('tensor',)
        method = 'tensor'

        def __init__(self, K, C, B, E, G, **kw):
            super().__init__(K, C, B, E, **kw)
            self.G = np.asarray(G, dtype=np.float64)
            if self.G.shape != (self.r, self.r, self.r):
                raise ValueError(f'G must have shape (r, r, r); got {self.G.shape}')

    base = h.second_order()
    model = TensorModel(base.K, base.C, base.B, base.E, np.ones((3, 3, 3)), dt=base.dt)
    loaded = load_model(model.save(tmp_path / 't.npz'))
    assert type(loaded) is TensorModel and loaded.G.shape == (3, 3, 3)
    _refused(h.with_arrays(model, tmp_path / 'bad.npz', G=np.ones((3, 3))), 'shape')


@pytest.mark.parametrize('change', [{'dt': 1e300}, {'dt': float('inf')}])
def test_predictor_and_info_refuse_absurd_dt(tmp_path, change) -> None:
    from soft_rom.cli.info import describe
    from soft_rom.predictor import Predictor

    path = h.with_header(h.discrete(), tmp_path / 'm.npz', **change)
    with pytest.raises(ModelFileError, match='dt|Infinity'):
        Predictor(path)
    with pytest.raises(ModelFileError, match='dt|Infinity'):
        describe(path)
    stiff = h.with_arrays(h.second_order(), tmp_path / 'k.npz', K=np.eye(3) * 1e300)
    with pytest.raises(ModelFileError):
        Predictor(stiff)
