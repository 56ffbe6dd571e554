"""README.md's Python tutorial (with the C++ tutorial's .lcm file) and docs/python.md's service
and action examples, run as printed."""
import os
import pathlib
import re
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
PYTHON_MD = ROOT / "docs" / "python.md"


# lcmx logs through spdlog's default logger, which writes to stdout; a run may log, e.g., that it
# removed shared memory of processes that died earlier (another test's). Compared without them.
LOG_LINE = re.compile(r"^\[\d{4}-\d\d-\d\d [\d:.]+\] \[\w+\] .*\n", re.M)


def program_output(stdout):
    return LOG_LINE.sub("", stdout)


def block_after(text, marker, lang):
    start = text.index(marker)
    m = re.compile(r"```%s\n(.*?)```" % lang, re.S).search(text, start)
    lines = m.group(1).splitlines()
    indent = min(len(l) - len(l.lstrip()) for l in lines if l.strip())
    return "\n".join(l[indent:] for l in lines) + "\n"


def test_readme_tutorial(lcmx_env, tmp_path):
    text = README.read_text()
    lcm_file = re.search(r"```\n\s*(package my_types;.*?)```", text, re.S).group(1)
    (tmp_path / "my_types").mkdir()
    (tmp_path / "my_types" / "temperature_t.lcm").write_text(
        "\n".join(l.strip() for l in lcm_file.splitlines()) + "\n")
    subprocess.run([os.environ["LCMX_LCM_GEN"], "--python", "my_types/temperature_t.lcm"],
                   cwd=tmp_path, check=True)
    (tmp_path / "thermo.py").write_text(block_after(text, "<!-- python-tutorial", "python"))
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), env["PYTHONPATH"]])
    out = subprocess.run([sys.executable, "thermo.py"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert program_output(out.stdout) == "21.5 C\n", (out.stdout, out.stderr)


def run_block(marker, tmp_path):
    (tmp_path / "example.py").write_text(block_after(PYTHON_MD.read_text(), marker, "python"))
    out = subprocess.run([sys.executable, "example.py"], cwd=tmp_path, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return program_output(out.stdout)


def test_python_md_service(lcmx_env, tmp_path):
    assert run_block("<!-- python-service", tmp_path) == "7\n"


def test_python_md_action(lcmx_env, tmp_path):
    assert run_block("<!-- python-action", tmp_path) == "at 1.0\nat 2.0\nat 3.0\nsucceeded 3\n"
