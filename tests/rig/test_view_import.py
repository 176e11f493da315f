"""fwk view when open3d cannot be imported: a missing system library (open3d's Linux wheel loads
libusb-1.0, absent on a fresh Debian or Ubuntu) is named with the package to install, distinct
from open3d not being installed; the import is monkeypatched to fail as each case fails."""
from __future__ import annotations

import builtins

import numpy as np
import pytest

from fwk.errors import FwkError

#: what ``import open3d`` (0.20, Debian 12) raises with libusb-1.0-0 removed (reproduced by
#: hiding the library in a mount namespace)
NO_LIBUSB = "libusb-1.0.so.0: cannot open shared object file: No such file or directory"


def _failing_import(monkeypatch, exc: BaseException) -> None:
    real = builtins.__import__

    def fake(name, *args, **kwargs):
        if name == "open3d" or name.startswith("open3d."):
            raise exc
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake)


@pytest.mark.parametrize("exc, expected", [
    (ImportError(NO_LIBUSB),
     "fwk view: open3d is installed, but the system library libusb-1.0.so.0 that it loads is missing: install the "
     "Debian/Ubuntu package libusb-1.0-0 (sudo apt-get install libusb-1.0-0)"),
    (OSError("libEGL.so.1: cannot open shared object file: No such file or directory"),
     "fwk view: open3d is installed, but the system library libEGL.so.1 that it loads is missing: install the "
     "Debian/Ubuntu package libegl1 (sudo apt-get install libegl1)"),
    (ImportError("libfoo-2.so.3: cannot open shared object file: No such file or directory"),
     "fwk view: open3d is installed, but the system library libfoo-2.so.3 that it loads is missing: install the "
     "system package that holds it (Debian/Ubuntu: apt-file search libfoo-2.so.3)"),
    (ModuleNotFoundError("No module named 'open3d'", name="open3d"),
     "fwk view needs the Python package open3d: pip install 'fwk[rig]' (or pip install open3d)"),
    (ImportError("numpy.core.multiarray failed to import\nmore"),
     "fwk view: open3d is installed but cannot be imported (ImportError: numpy.core.multiarray failed to import)"),
])
def test_the_error_names_what_is_missing(monkeypatch, exc, expected):
    from fwk.view import _o3d

    _failing_import(monkeypatch, exc)
    with pytest.raises(FwkError) as info:
        _o3d()
    assert str(info.value) == expected
    if "system library" in expected:
        assert "pip install" not in expected and "needs the Python package" not in expected


def test_fwk_view_screenshot_without_libusb_is_one_line_exit_2(monkeypatch, tmp_path, capsys):
    """The command: the rig is read (no open3d needed), the picture needs open3d: one line, exit 2."""
    from fwk.cli import main

    obj = tmp_path / "tri.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    _failing_import(monkeypatch, ImportError(NO_LIBUSB))
    assert main(["view", str(obj), "--screenshot", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("fwk: error: fwk view: open3d is installed, but the system library libusb-1.0.so.0 that it loads "
                   "is missing: install the Debian/Ubuntu package libusb-1.0-0 (sudo apt-get install libusb-1.0-0)")
    assert not (tmp_path / "x.png").exists()
    # and the window alike (it fails before opening anything)
    from fwk.view import Rig, open_window

    with pytest.raises(FwkError, match="libusb-1.0-0"):
        open_window(Rig(np.zeros((3, 3)), np.array([[0, 1, 2]]), [], np.zeros((0, 3, 3))))
