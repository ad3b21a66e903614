"""safe_pickle: numpy pickles of every protocol load equal; damaged dtype states, bogus array data and other globals are refused."""

from __future__ import annotations

import io
import pickle

import numpy as np
import pytest
import scipy.sparse as sp

from deliffas.io.infra.safe_pickle import UnsafePickleError, load_numpy_pickle

VALUE = {"K": [np.eye(3), np.arange(6, dtype=">i4").reshape(2, 3)], "f": np.asfortranarray(np.ones((2, 3), np.float32)),
         "s": np.float64(2.5), "names": ["cam0", "cam1"], "t": (1, 2.0, None, b"x"), "obj": np.array([{"a": 1}, "b"], object),
         "empty": np.zeros((0, 3)), "text": np.array(["ab", "c"])}


def _equal(a, b) -> None:
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            _equal(a[k], b[k])
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b)
        for x, y in zip(a, b):
            _equal(x, y)
    elif isinstance(a, np.ndarray):
        assert a.dtype.newbyteorder("=") == b.dtype.newbyteorder("=") and a.shape == b.shape  # values may come native
        if a.dtype.hasobject:
            _equal(a.tolist(), b.tolist())
        else:
            np.testing.assert_array_equal(a, b)
    else:
        assert a == b and type(a) is type(b)


@pytest.mark.parametrize("protocol", [2, 3, 4, 5])
def test_numpy_values_round_trip(protocol):
    _equal(VALUE, load_numpy_pickle(pickle.dumps(VALUE, protocol=protocol)))


def test_np_save_of_a_dict_and_sparse_classes():
    a = np.empty((), object)
    a[()] = VALUE
    buf = io.BytesIO()
    np.save(buf, a)
    data = buf.getvalue()
    start = data.index(b"\n", 10) + 1  # after the .npy header
    _equal(VALUE, load_numpy_pickle(data[start:]).item())
    m = sp.csc_matrix(np.array([[0, 1.5], [2, 0]]))
    with pytest.raises(UnsafePickleError, match="scipy.sparse"):
        load_numpy_pickle(pickle.dumps(m, protocol=2))
    back = load_numpy_pickle(pickle.dumps(m, protocol=2), lambda mod, name: sp.csc_matrix if name == "csc_matrix" else None)
    np.testing.assert_array_equal(back.toarray(), m.toarray())


def _object_array_pickle() -> bytes:
    data = pickle.dumps(np.array([b"abc", {"k": 1}], object), protocol=4)
    assert data.count(b"J\xff\xff\xff\xffJ\xff\xff\xff\xffK?") == 1  # the dtype state: elsize, alignment, flags 63
    return data


@pytest.mark.parametrize("old,new", [(b"J\xff\xff\xff\xffJ\xff\xff\xff\xffK?", b"J\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00"),
                                     (b"J\xff\xff\xff\xffJ\xff\xff\xff\xffK?", b"J\x01\x00\x00\x00J\xff\xff\xff\xffK?")])
def test_a_damaged_dtype_state_is_not_applied(old, new):
    """Flags or item size of a dtype state changed in the file: numpy would apply them to an object dtype and
    lose track of references (the process crashed under fuzzing); only the byte order is used here."""
    out = load_numpy_pickle(_object_array_pickle().replace(old, new))
    assert out.dtype == object and out[0] == b"abc" and out[1] == {"k": 1}


class _Reduce:
    def __init__(self, fn, args):
        self.fn, self.args = fn, args

    def __reduce__(self):
        return self.fn, self.args


@pytest.mark.parametrize("payload,match", [
    (_Reduce(np.ndarray, ((2,), "f8", b"\x00" * 16)), "refusing to call numpy.ndarray"),  # the class itself is not callable from a stream
    (_Reduce(np.dtype, ("V8",)), "refusing dtype"),
    (_Reduce(print, ("hi",)), r"refusing to load '__builtin__\.print'"),
    (_Reduce(np.frombuffer, (b"\x00" * 8,)), "numpy"),
])
def test_other_calls_are_refused(payload, match):
    with pytest.raises(UnsafePickleError, match=match):
        load_numpy_pickle(pickle.dumps(payload, protocol=2))


def test_array_data_must_fit_its_shape():
    data = pickle.dumps(np.arange(4.0), protocol=2)
    with pytest.raises(UnsafePickleError, match=r"shape \(5,\) and float64 must be 40 bytes"):
        load_numpy_pickle(data.replace(b"K\x04\x85", b"K\x05\x85"))  # shape (5,) over 4 floats
    with pytest.raises(UnsafePickleError, match="damaged pickle"):
        load_numpy_pickle(data[: len(data) // 2])
