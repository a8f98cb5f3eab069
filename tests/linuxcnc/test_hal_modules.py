"""compd.io.hal_modules: LinuxCNC's `hal` and `linuxcnc` loaded from Debian's files into the venv's Python,
a missing or unloadable file as one line of BadInput, only successes cached, the process's signal handlers kept.

The cases that need a fresh interpreter (a first attempt that fails; `_hal`'s one-time initialisation) run
in a child Python."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from compd.core.errors import BadInput
from compd.io import hal_modules

ROOT = Path(__file__).resolve().parents[2]


def need_linuxcnc() -> Path:
    """The folder of LinuxCNC's modules, or the test fails (LinuxCNC is installed by `make sysdeps`)."""
    reason = hal_modules.available()
    if reason is not None:
        pytest.fail(reason, pytrace=False)
    return hal_modules.folder()


def child(script: str, **env: str) -> subprocess.CompletedProcess[str]:
    """Run `script` in a fresh venv Python (the worktree's compd) with `env` added."""
    full = {k: v for k, v in os.environ.items() if k != hal_modules.ENV}
    full.update(env, PYTHONPATH=str(ROOT))
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script)],
        env=full,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def test_the_modules_load_from_debians_files_without_dist_packages_on_the_path():
    where = need_linuxcnc()
    hal, linuxcnc = hal_modules.load()
    assert hal_modules.load() == (hal, linuxcnc)  # cached
    assert Path(hal.__file__) == where / "hal.py"
    assert Path(linuxcnc.__file__).parent == where and linuxcnc.__name__ == "linuxcnc"
    assert sys.modules["hal"] is hal and sys.modules["linuxcnc"] is linuxcnc
    assert sys.modules["_hal"].__file__.startswith(str(where / "_hal."))
    assert hal.HAL_S32 != hal.HAL_FLOAT and callable(hal.component)  # hal.py's names, from _hal
    assert linuxcnc.MODE_AUTO != linuxcnc.MODE_MANUAL and callable(linuxcnc.stat)
    assert str(where) not in sys.path and "/usr/lib/python3/dist-packages" not in sys.path


def test_an_empty_folder_is_one_line_of_bad_input_and_a_later_good_load_still_works(tmp_path):
    need_linuxcnc()
    # a fresh interpreter whose first attempt fails: nothing of it may be cached or left in sys.modules
    done = child(
        f"""
        import os, sys
        from compd.core.errors import BadInput
        from compd.io import hal_modules
        line = hal_modules.available()
        print(line)
        try:
            hal_modules.load()
        except BadInput as exc:
            assert str(exc) == line, (str(exc), line)
        else:
            raise SystemExit("no BadInput")
        assert not {{"hal", "_hal", "linuxcnc"}} & set(sys.modules)
        del os.environ["{hal_modules.ENV}"]
        hal, linuxcnc = hal_modules.load()
        assert hal_modules.available() is None
        print("loaded", hal.__file__)
    """,
        **{hal_modules.ENV: str(tmp_path)},
    )
    assert done.returncode == 0, done.stderr
    line, loaded = done.stdout.splitlines()
    assert line == (
        f"LinuxCNC's Python module hal is not installed ({tmp_path}/hal.py): install Debian's "
        f"linuxcnc-uspace (make sysdeps), or set {hal_modules.ENV} to the folder that holds "
        f"LinuxCNC's hal.py"
    )
    assert loaded == f"loaded {hal_modules.DEFAULT_FOLDER}/hal.py"
    assert "Traceback" not in done.stderr


def test_a_folder_without_linuxcnc_names_it_and_leaves_no_half_loaded_modules(tmp_path):
    where = need_linuxcnc()
    hal_so = next(where.glob("_hal.cpython-*.so"))
    (tmp_path / "hal.py").symlink_to(where / "hal.py")
    (tmp_path / hal_so.name).symlink_to(hal_so)
    done = child(
        f"""
        import os, sys
        from compd.core.errors import BadInput
        from compd.io import hal_modules
        print(hal_modules.available())
        assert not {{"hal", "_hal", "linuxcnc"}} & set(sys.modules), sorted(sys.modules)
        os.environ["{hal_modules.ENV}"] = "{where}"
        hal, linuxcnc = hal_modules.load()
        print("loaded", linuxcnc.__name__)
    """,
        **{hal_modules.ENV: str(tmp_path)},
    )
    assert done.returncode == 0, done.stderr
    line, loaded = done.stdout.splitlines()
    assert line.startswith(f"LinuxCNC's Python module linuxcnc is not installed ({tmp_path}/linuxcnc.cpython-")
    assert loaded == "loaded linuxcnc"


def test_a_file_that_does_not_load_or_is_for_another_python_is_one_line(tmp_path, monkeypatch):
    where = need_linuxcnc()
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "hal.py").symlink_to(where / "hal.py")
    suffix = next(where.glob("_hal.cpython-*.so")).name[len("_hal") :]
    (broken / f"_hal{suffix}").write_text("not an ELF file\n")
    (broken / f"linuxcnc{suffix}").symlink_to(where / f"linuxcnc{suffix}")
    monkeypatch.setenv(hal_modules.ENV, str(broken))
    with pytest.raises(BadInput) as caught:
        hal_modules.load()
    message = str(caught.value)
    assert message.startswith(f"LinuxCNC's Python module _hal does not load ({broken}/_hal{suffix}: ImportError: ")
    assert "\n" not in message and message.endswith(
        "(make sysdeps), or set COMPD_LINUXCNC_PYTHON to the folder that holds LinuxCNC's hal.py"
    )

    other = tmp_path / "other"
    other.mkdir()
    (other / "hal.py").symlink_to(where / "hal.py")
    (other / "_hal.cpython-39-x86_64-linux-gnu.so").write_text("")
    monkeypatch.setenv(hal_modules.ENV, str(other))
    version = f"{sys.version_info.major}.{sys.version_info.minor}"
    assert hal_modules.available() == (
        f"LinuxCNC's Python module _hal in {other} is built for another Python (_hal.cpython-39-x86_64-linux-gnu.so), "
        f"compd runs Python {version}: run compd with the Python that LinuxCNC was built for"
    )


@pytest.mark.parametrize("where", ["main thread", "other thread"])
def test_loading_keeps_the_processs_signal_handlers(where):
    need_linuxcnc()
    # _hal's initialisation sets SIGTERM to raise KeyboardInterrupt (compd installs its handlers first), and
    # from a thread other than the main one that call fails with a traceback on stderr
    done = child(f"""
        import signal, threading
        from compd.io import hal_modules

        def on_term(signum, frame):
            pass

        signal.signal(signal.SIGTERM, on_term)
        got = []
        if {where == "main thread"}:
            got.append(hal_modules.available())
        else:
            loader = threading.Thread(target=lambda: got.append(hal_modules.available()))
            loader.start()
            loader.join()
        assert got == [None], got
        assert signal.getsignal(signal.SIGTERM) is on_term, signal.getsignal(signal.SIGTERM)
        assert signal.signal.__module__ == "signal"
        print("kept")
    """)
    assert (done.returncode, done.stdout, done.stderr) == (0, "kept\n", "")
