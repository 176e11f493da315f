"""fwk.safeio: model states and checkpoints as data only (safetensors + JSON structure), verified."""
from __future__ import annotations

import io
import json
import pathlib
import struct
import subprocess
import sys

import numpy as np
import pytest
import torch

from fwk.errors import DataError
from fwk.safeio import (LegacyFormatError, UnsafeStateError, dumps_state, load_json, load_npz, load_state,
                        loads_state, pickled_files, save_state)
from fwk.testing.model import assert_same_state


def _state():
    sparse = torch.sparse_coo_tensor(torch.tensor([[0, 2], [1, 0]]), torch.tensor([1.5, -2.0]), (3, 2))
    return {
        "w": torch.randn(4, 3), "half": torch.ones(2, dtype=torch.bfloat16), "empty": torch.zeros(0, 5),
        "idx": torch.arange(5), "mask": torch.tensor([True, False]), "sparse": sparse,
        "np": np.arange(6, dtype=np.float32).reshape(2, 3), "u16": np.arange(3, dtype=np.uint16),
        "np_scalar": np.float64(0.25), "np_int": np.int32(-3), "np_bool": np.bool_(True),
        7: "an int key", None: None, 2.5: "a float key", True: [1, 2.0, "x", None, False],
        "tuple": (1, (2, 3), [np.ones(2)]), "nan": float("nan"), "inf": -float("inf"), "big": 2 ** 70,
        "nested": {"a": {"b": {"c": torch.tensor(3.0)}}},
    }


def test_round_trip_keeps_types_and_values():
    s = _state()
    back, meta = loads_state(dumps_state(s, {"label": "x", "n": 3}))
    assert_same_state(s, back)
    assert meta == {"label": "x", "n": 3}
    assert isinstance(back["np"], np.ndarray) and isinstance(back["w"], torch.Tensor)
    assert back["sparse"].layout == torch.sparse_coo and torch.equal(back["sparse"].to_dense(), s["sparse"].to_dense())
    assert type(back["np_scalar"]) is np.float64 and type(back["tuple"]) is tuple


def test_assert_same_state_can_fail():
    with pytest.raises(AssertionError):
        assert_same_state({"a": np.ones(2)}, {"a": torch.ones(2)})
    with pytest.raises(AssertionError):
        assert_same_state({"a": (1, 2)}, {"a": [1, 2]})


@pytest.mark.parametrize("value, where", [
    (pathlib.Path("/x"), "a.b"), (lambda: 0, "a.b"), (object(), "a.b"), (np.array(["s"]), "a.b"),
    (np.array([1 + 2j]), "a.b"), (torch.ones(2, dtype=torch.complex64), "a.b"), ({1, 2}, "a.b"),
])
def test_anything_but_plain_data_is_refused_naming_where(value, where):
    with pytest.raises(UnsafeStateError, match=f"^{where}: "):
        dumps_state({"a": {"b": value}})


def test_a_key_of_another_type_is_refused():
    with pytest.raises(UnsafeStateError, match="a key of type tuple"):
        dumps_state({(1, 2): 3})


def _tensor_start(data: bytes) -> int:
    return 8 + struct.unpack("<Q", data[:8])[0]


def test_changed_bytes_are_refused(tmp_path):
    data = dumps_state({"w": torch.arange(100.0)})
    flipped = bytearray(data)
    flipped[_tensor_start(data) + 17] ^= 0x04
    with pytest.raises(DataError, match="do not match the SHA-256"):
        loads_state(bytes(flipped), "f")
    for cut in (3, 20, len(data) - 1):
        with pytest.raises(DataError, match="^f: "):
            loads_state(data[:cut], "f")


def _second_save(state, meta=None) -> bytes:
    """The naive reference of ``dumps_state``: saved once to hash the tensor bytes, then again with
    the hash in the header (as fwk wrote states before 2026-12-07)."""
    from safetensors.torch import save

    from fwk.safeio import FORMAT, _encode, _split
    tensors: dict = {}
    structure = _encode(state, "", tensors, torch)
    fields = {"format": FORMAT, "structure": json.dumps(structure), "meta": json.dumps(meta or {})}
    first = save(tensors, metadata=fields)
    start, _ = _split(first)
    fields["sha256"] = __import__("hashlib").sha256(first[start:]).hexdigest()
    return save(tensors, metadata=fields)


def _parts(data: bytes):
    start = _tensor_start(data)
    return json.loads(data[8:start]), data[start:]


@pytest.mark.parametrize("clash", [False, True])
def test_the_hash_written_in_place_is_the_second_saves(monkeypatch, clash):
    """One save, its placeholder overwritten by the hash: the same header (metadata, offsets) and tensor
    bytes as saving twice; where the placeholder is not once in the header (here the meta holds it too),
    the second save is made."""
    from fwk import safeio
    state = {"w": torch.randn(300, 7), "i": torch.arange(11), "n": np.linspace(0, 1, 5), "x": [1, "a"]}
    meta = {"label": "0" * 64} if clash else {"label": "m"}
    if clash:
        monkeypatch.setattr(safeio.secrets, "token_hex", lambda n: "0" * (2 * n))
    got, want = _parts(dumps_state(state, meta)), _parts(_second_save(state, meta))
    assert got == want
    assert got[0]["__metadata__"]["sha256"] == __import__("hashlib").sha256(got[1]).hexdigest()
    back, m = loads_state(dumps_state(state, meta))
    assert_same_state(state, back)
    assert m == meta


def _with_header(data: bytes, edit) -> bytes:
    start = _tensor_start(data)
    header = json.loads(data[8:start])
    edit(header)
    raw = json.dumps(header).encode()
    raw += b" " * (-len(raw) % 8)
    return struct.pack("<Q", len(raw)) + raw + data[start:]


@pytest.mark.parametrize("edit, match", [
    (lambda h: h["__metadata__"].update(structure='{"d": [["w", {"t": "9"}]]}'), "structure is malformed"),
    (lambda h: h["__metadata__"].update(structure='{"d": [["w", {"x": 1}]]}'), "structure is malformed"),
    (lambda h: h["__metadata__"].update(structure='{"l": []}'), "not in its structure"),
    (lambda h: h["__metadata__"].update(structure="[" * 5000), "structure is malformed"),
    (lambda h: h["__metadata__"].update(format="other"), "not an fwk state file"),
    (lambda h: h.pop("__metadata__"), "not an fwk state file"),
])
def test_a_malformed_header_is_refused(edit, match):
    data = dumps_state({"w": torch.arange(4.0)})
    with pytest.raises(DataError, match=match):
        loads_state(_with_header(data, edit), "f")


def test_a_pickle_is_refused_naming_fwk_convert(tmp_path):
    run = tmp_path / "run"
    (run / "models").mkdir(parents=True)
    (run / "recipe.yaml").write_text("task: reconstruct\n")
    p = run / "models" / "m.safetensors"
    torch.save({"w": torch.ones(2)}, p)
    with pytest.raises(LegacyFormatError, match=f"fwk convert {run} --trust"):
        load_state(p)
    buf = io.BytesIO()
    torch.save({"w": 1}, buf, _use_new_zipfile_serialization=False)  # the legacy (non-zip) pickle format
    p.write_bytes(buf.getvalue())
    with pytest.raises(LegacyFormatError):
        load_state(p)
    (run / "models" / "old.pt").write_bytes(b"\x80\x04x")
    assert pickled_files(run) == [run / "models" / "m.safetensors", run / "models" / "old.pt"]


def test_save_is_atomic_and_load_names_a_missing_file(tmp_path):
    p = save_state(tmp_path / "a" / "s.safetensors", {"x": 1})
    assert load_state(p) == {"x": 1} and not list(p.parent.glob("*.tmp"))
    with pytest.raises(DataError, match="missing"):
        load_state(tmp_path / "nope")


def test_npz_and_json_readers(tmp_path):
    np.savez(tmp_path / "a.npz", x=np.ones(2))
    assert load_npz(tmp_path / "a.npz")["x"].tolist() == [1, 1]
    np.savez(tmp_path / "o.npz", x=np.array([{}], dtype=object))
    with pytest.raises(DataError, match="o.npz: not a readable .npz"):
        load_npz(tmp_path / "o.npz")
    (tmp_path / "g.npz").write_bytes(b"garbage")
    with pytest.raises(DataError, match="g.npz: not an .npz file"):
        load_npz(tmp_path / "g.npz")
    (tmp_path / "m.json").write_text("[1]")
    with pytest.raises(DataError, match="expected a JSON object"):
        load_json(tmp_path / "m.json")
    (tmp_path / "m.json").write_bytes(b"\xff{")
    with pytest.raises(DataError, match="not valid JSON"):
        load_json(tmp_path / "m.json")


def test_importing_safeio_does_not_import_torch():
    code = "import sys, fwk.safeio, fwk.lifecycle, fwk.convert; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.stdout.strip() == "False", out.stderr


def test_a_state_whose_header_length_starts_with_0x80_is_no_pickle(tmp_path):
    """One header length in 256 has 0x80 as its low byte, pickle protocol 2's first byte: such a
    state file (a checkpoint whose stored paths made it so) is read as a state, not refused as an
    earlier fwk's pickle; a real pickle still is one."""
    from fwk.safeio import file_is_pickle, load_state, save_state

    for pad in range(600):
        path = tmp_path / f"s{pad}.safetensors"
        save_state(path, {"w": np.arange(3.0), "dir": "x" * pad})
        if path.read_bytes()[0] == 0x80:
            break
    else:
        raise AssertionError("no padding gave a header length with low byte 0x80")
    assert not file_is_pickle(path)
    assert load_state(path)["dir"] == "x" * pad
    buf = io.BytesIO()
    torch.save({"w": torch.zeros(2)}, buf, _use_new_zipfile_serialization=False)  # starts with 0x80
    legacy = tmp_path / "legacy.pt"
    legacy.write_bytes(buf.getvalue())
    assert legacy.read_bytes()[0] == 0x80 and file_is_pickle(legacy)


def test_equal_arrays_are_stored_once_and_come_back_as_copies():
    tri = np.arange(300, dtype=np.int64).reshape(100, 3)
    mean = np.linspace(0, 1, 600).reshape(200, 3)
    state = {"a": tri, "b": {"F": tri.copy(), "mean": mean}, "c": [mean.copy(), tri[:50].copy()]}
    once = dumps_state({"a": tri, "b": {"mean": mean}, "c": [tri[:50].copy()]})
    data = dumps_state(state)
    assert len(data) < len(once) + 200  # the repeats cost a reference each, not their bytes
    back, _ = loads_state(data, "f")
    assert_same_state(back, state)
    back["a"][0, 0] = -1  # copies, not views of one buffer
    assert back["b"]["F"][0, 0] == 0


@pytest.mark.parametrize("structure, match", [
    ('{"d": [["x", {"r": "0"}], ["w", {"n": "0"}]]}', "no array decoded before"),  # a reference before its array
    ('{"d": [["w", {"n": "0"}], ["x", {"r": "7"}]]}', "no array decoded before"),
    ('{"l": [{"n": "0"}, ' + ", ".join(['{"r": "0"}'] * 3) + "]}", "copy more than"),  # amplification
])
def test_references_are_checked(structure, match):
    data = dumps_state({"w": np.arange(4.0)})
    with pytest.raises(DataError, match=match):
        loads_state(_with_header(data, lambda h: h["__metadata__"].update(structure=structure)), "f")
    ok = _with_header(data, lambda h: h["__metadata__"].update(structure='{"l": [{"n": "0"}, {"r": "0"}]}'))
    # the sha256 covers the tensor bytes only: an edited structure with a valid reference loads
    assert [list(x) for x in loads_state(ok, "f")[0]] == [[0.0, 1.0, 2.0, 3.0]] * 2


def test_tensors_in_one_memory_are_saved_apart_and_the_rest_read_in_place(tmp_path):
    """Parameters are read where they lie (not copied first); tensors that share memory (views of
    one buffer, as a tied weight gives) are still saved, each with its own values."""
    base = torch.arange(24.0)
    state = {"whole": base, "view": base[4:10], "tied": base.view(4, 6), "other": torch.ones(3),
             "empty": torch.zeros(0), "empty2": torch.zeros(0, 2)}
    p = save_state(tmp_path / "s.safetensors", state)
    back = load_state(p)
    assert_same_state(state, back)
    back["whole"][0] = -1.0
    assert back["view"][0] == 4.0 and back["tied"][0, 0] == 0.0 and base[0] == 0.0
    assert_same_state(loads_state(dumps_state(state))[0], back | {"whole": state["whole"]})
