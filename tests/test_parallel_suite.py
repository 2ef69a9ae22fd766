"""The suite runs across the cores (scripts/test.sh: ``pytest -n auto --dist loadgroup``)."""

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_xdist_groups_keep_their_tests_on_one_worker(tmp_path):
    """The tests of one ``xdist_group`` (a file's, by ``pytestmark``) all run on one worker
    (tests/conftest.py: the module-scoped fixtures of such a file are built once); the others
    are spread over the workers."""
    shutil.copy(ROOT / "tests" / "conftest.py", tmp_path / "conftest.py")
    (tmp_path / "test_grouped.py").write_text(
        "import pytest\n\npytestmark = pytest.mark.xdist_group('file')\n\n\n"
        "@pytest.mark.parametrize('i', range(6))\ndef test_a(i):\n    pass\n")
    (tmp_path / "test_free.py").write_text(
        "import time\n\nimport pytest\n\n\n@pytest.mark.parametrize('i', range(6))\n"
        "def test_b(i):\n    time.sleep(0.2)\n")
    done = subprocess.run([sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadgroup", "-v",
                           "-p", "no:cacheprovider"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:]

    def workers(name):
        return {line.split()[0] for line in done.stdout.splitlines()
                if name in line and "PASSED" in line}

    assert len(workers("test_grouped.py::test_a")) == 1, done.stdout[-3000:]
    assert len(workers("test_free.py::test_b")) == 2, done.stdout[-3000:]
