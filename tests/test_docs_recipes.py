"""The manual's multi-step recipes, run as written.

A recipe is a fenced block of README.md or ``docs/*.md`` whose info string names it:
```` ```bash recipe=record-replay ````. Each test finds its recipe by name and runs its lines in a
temp dir that looks like a checkout (``.venv/bin/telesurg`` and ``deploy/`` are links to this
one) inside a private network namespace (``unshare --net``, as root), so the recipes' default
router port 127.0.0.1:7447 is free whatever else runs on this host; without root the process
tests skip and say why. Each checks what a user would: exit codes, the figures printed.

Also here, what a newcomer meets in the first hour: ``telesurg --version``, a command with no site
running, ``deploy/console.sh`` without a keyring.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
BIN = Path(sys.executable).parent
RECIPE = re.compile(r"^```+\s*(\w+)\s+.*\brecipe=([\w-]+)")
NAMES = (
    "record-replay",
    "plas-pty",
    "messages-node",
    "messages-codec",
    "two-host-keys",
    "plugin-robot",
    "plugin-device",
    "plugin-rule",
    "learning",
)


def recipe(name: str) -> tuple[str, list[str]]:
    """(language, lines) of the block named ``name`` (continuation lines joined)."""
    for path in DOCS:
        lines = path.read_text(encoding="utf-8").splitlines()
        for i, line in enumerate(lines):
            m = RECIPE.match(line)
            if m and m.group(2) == name:
                body: list[str] = []
                for text in lines[i + 1 :]:
                    if text.startswith("```"):
                        break
                    if body and body[-1].endswith("\\"):
                        body[-1] = body[-1][:-1] + " " + text.strip()
                    else:
                        body.append(text)
                return m.group(1), body
    raise AssertionError(f"no block marked recipe={name} in README.md or docs/")


def commands(name: str) -> list[str]:
    """The shell lines of recipe ``name`` (blank lines dropped)."""
    lang, lines = recipe(name)
    assert lang == "bash", (name, lang)
    return [line for line in lines if line.strip()]


def checkout(tmp: Path) -> dict[str, str]:
    """``tmp`` as a user's checkout: ``.venv/bin/telesurg`` and ``deploy/``; the environment."""
    (tmp / ".venv").mkdir()
    (tmp / ".venv" / "bin").symlink_to(BIN)
    (tmp / "deploy").symlink_to(ROOT / "deploy")
    keys = tmp / "state"  # a keyring of its own (telesurg up makes it)
    return dict(os.environ, PATH=f"{BIN}:{os.environ['PATH']}", XDG_STATE_HOME=str(keys), WORK=str(tmp))


def tail(path: Path, n: int = 15) -> str:
    """The last ``n`` lines of a file."""
    return "\n".join(path.read_text(errors="replace").splitlines()[-n:])


def in_netns(script: str, tmp: Path, timeout: float) -> subprocess.CompletedProcess[str]:
    """Run bash ``script`` in ``tmp`` in a network namespace of its own (loopback only)."""
    if os.geteuid() != 0 or not shutil.which("unshare") or not shutil.which("ip"):
        pytest.skip("needs root, unshare and ip: a private loopback where port 7447 is free")
    full = f'set -u\nip link set lo up\ncd "$WORK"\n{script}'
    with subprocess.Popen(
        ["unshare", "--net", "bash", "-c", full],
        env=checkout(tmp),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group: a timeout ends everything it started
    ) as p:
        try:
            out, err = p.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            out, err = "", ""
            for sig, grace in ((signal.SIGINT, 15.0), (signal.SIGKILL, 5.0)):
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, sig)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    out, err = p.communicate(timeout=grace)
                    break
            # what it printed and the end of each log it wrote: where it stuck
            logs = sorted(tmp.glob("*.log")) + sorted(tmp.glob("*.txt"))
            tails = [f"--- {f.name}\n{tail(f)}" for f in logs]
            raise AssertionError(
                f"the recipe did not end within {timeout} s:\n{script}\n--- stdout\n{out}\n--- stderr\n"
                f"{err[-2000:]}\n" + "\n".join(tails)
            ) from None
    return subprocess.CompletedProcess(p.args, p.returncode, out, err)


def errors(text: str) -> list[str]:
    return [line for line in text.splitlines() if " ERROR " in line or "Traceback" in line]


def stop_errors(text: str) -> list[str]:
    """The errors a site logged from the launcher's "stopping …" on (an orderly stop logs none;
    before it, a loaded host may rightly hold with an ERROR)."""
    at = text.find("launcher INFO telesurg.launcher: stopping ")
    assert at >= 0, f"the launcher never said it was stopping:\n{text[-3000:]}"
    gone = [line for line in text.splitlines() if "master_capture not alive" in line and " ERROR " in line]
    return errors(text[at:]) + gone


def two_host_keys(tmp: Path) -> tuple[Path, Path]:
    """docs/deploy.md's key export (slave machine) and import (console machine), each line run
    as written in ``tmp`` with each machine's own state folder; (the slave site's keyring, the
    console machine's). The slave's keyring is made first, as its first ``telesurg up`` does."""
    from telesurg.shared import auth

    machine = ""
    homes = {m: tmp / f"{m}-state" for m in ("slave", "console")}
    site_keys = auth.init_keyring(homes["slave"] / "telesurg" / "lab" / "keys", auth.IDENTITIES)
    for line in commands("two-host-keys"):
        if m := re.match(r"#\s*(slave|console) machine", line):
            machine = m.group(1)
            continue
        if line.lstrip().startswith("#"):
            continue
        assert machine, f"{line!r}: on which machine? (a '# slave machine' line first)"
        env = dict(os.environ, PATH=f"{BIN}:{os.environ['PATH']}", XDG_STATE_HOME=str(homes[machine]))
        env.pop("TELESURG_KEYS", None)
        r = subprocess.run(["bash", "-c", line], cwd=tmp, env=env, capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, f"{machine} machine: {line}\n{r.stdout}{r.stderr}"
    return site_keys, homes["console"] / "telesurg" / "lab" / "keys"


# --------------------------------------------------------------------------- the blocks


def test_every_recipe_is_marked() -> None:
    for name in NAMES:
        assert recipe(name)[1], name


def test_the_two_host_key_split_as_written(tmp_path: Path) -> None:
    """docs/deploy.md: the console machine ends up with its identities' keys and a link to the
    site; the site's keyring no longer signs as them (tests/test_split_keys_process.py drives a
    site with these keyrings)."""
    from telesurg.shared import auth

    site_keys, console_keys = two_host_keys(tmp_path)
    site, console = auth.Keyring.load(site_keys), auth.Keyring.load(console_keys)
    assert console.identities() == ["console", "master_capture"] and list(console.links) == ["slave-site"]
    assert "console" not in site.identities() and "master_capture" not in site.identities()
    assert list(site.links) == ["console"]


# --------------------------------------------------------------------------- record → replay


@pytest.mark.process
@pytest.mark.timeout(420)
def test_record_then_replay_as_written(tmp_path: Path) -> None:
    """README: a session recorded from its start, replayed into a fresh site: exit 0, the slave
    did the same; both sites stop without an ERROR in any service's log."""
    first, second = commands("record-replay")
    script = f"""
{first} > record.log 2>&1
echo "record exit $?"
{second} > replay.log 2>&1
echo "replay exit $?"
"""
    r = in_netns(script, tmp_path, 400)
    rec = (tmp_path / "record.log").read_text() if (tmp_path / "record.log").exists() else ""
    rep = (tmp_path / "replay.log").read_text() if (tmp_path / "replay.log").exists() else ""
    print(rep[-3000:])
    assert "record exit 0" in r.stdout, f"{r.stdout}{r.stderr}\n{rec[-4000:]}"
    assert not stop_errors(rec), "an orderly stop logged errors:\n" + "\n".join(stop_errors(rec))
    assert "replay exit 0" in r.stdout, f"{r.stdout}{r.stderr}\n{rep[-4000:]}"
    report = json.loads((tmp_path / "diff.json").read_text())
    arm = report["arms"]["arm1"]
    print(f"replay: {arm['samples']} samples, RMS {arm['rms_max_rad']} rad, max {arm['max_rad']} rad")
    assert report["verdict"]["exit"] == 0 and arm["live_follow_s"] is not None
    assert arm["samples"] > 100 and arm["rms_max_rad"] <= 0.02
    assert not stop_errors(rep), "an orderly stop logged errors:\n" + "\n".join(stop_errors(rep))


# --------------------------------------------------------------------------- PLAS on a pty

PLAS_SCRIPT = """
{wrong} > wrong-board.txt 2> wrong-board.log &
WRONG=$!
{up} > refused.log 2>&1
echo "refused up exit $?"
kill -INT $WRONG; wait $WRONG
{board} > board.txt 2> board.log &
BOARD=$!
{up} > up.log 2>&1 &
UP=$!
for i in $(seq 900); do
  [ "$(grep -c 'teleop ENGAGING → ENABLED' up.log)" -ge 2 ] && break
  kill -0 $UP 2>/dev/null || break
  sleep 0.2
done
sleep 2
kill -INT $UP; wait $UP
echo "up exit $?"
kill -INT $BOARD; wait $BOARD
echo "board exit $?"
"""


@pytest.mark.process
@pytest.mark.timeout(420)
def test_the_plas_site_on_an_emulated_board_as_written(tmp_path: Path) -> None:
    """docs/robots.md (Hardware): the emulated board the PLAS site expects, then ``up``: both arms follow
    the master once its operator presses the pedal; Ctrl-C stops it cleanly. The same with a
    board the site does not expect (the default calibration): ``up`` exits 1 naming the cause."""
    board, up = commands("plas-pty")
    assert board.endswith(" &") and "--config-dir deploy/plas" in board
    wrong = board.replace(" --config-dir deploy/plas", "")[:-2]  # the default board: 400 counts/rev
    script = PLAS_SCRIPT.format(wrong=wrong, board=board[:-2], up=up.split("#")[0].strip())
    r = in_netns(script, tmp_path, 400)
    log = (tmp_path / "up.log").read_text() if (tmp_path / "up.log").exists() else ""
    refused = (tmp_path / "refused.log").read_text()
    assert "refused up exit 1" in r.stdout, f"{r.stdout}{r.stderr}\n{refused[-3000:]}"
    assert "telesurg up: master_capture published nothing for master m1" in refused
    assert "counts_per_rev=400, configured 1600" in refused, refused[-2000:]
    assert "up exit 0" in r.stdout and "board exit 0" in r.stdout, f"{r.stdout}{r.stderr}\n{log[-4000:]}"
    for arm in ("arm1", "arm2"):
        assert f"[{arm}] teleop ENGAGING → ENABLED" in log, log[-4000:]
    assert "clutch pressed at start" not in log  # the operator's press is a press
    assert not stop_errors(log), "an orderly stop logged errors:\n" + "\n".join(stop_errors(log))
    sent = re.search(r"master_capture .* sent (\d+) samples", log)
    assert sent and int(sent.group(1)) > 100, log[-3000:]


# --------------------------------------------------------------------------- plugins

PLUGIN_SCRIPT = """
ln -s {root}/tests tests
{up} > up.log 2>&1 &
UP=$!
for i in $(seq 450); do
  grep -qF {until} up.log && break
  kill -0 $UP 2>/dev/null || break
  sleep 0.2
done
sleep 1
kill -INT $UP; wait $UP
echo "up exit $?"
"""


@pytest.mark.process
@pytest.mark.timeout(400)
def test_the_plugin_examples_as_written(tmp_path: Path) -> None:
    """docs/extending.md: each plugin's ``telesurg up`` line as written in a checkout — the
    fourth robot follows its master through its own mapping, the plugin device drives the arm,
    the plugin rule holds it with its cause; Ctrl-C stops each site cleanly."""
    cases = {
        "plugin-robot": "'[arm1] teleop ENGAGING → ENABLED'",
        "plugin-device": "'[arm1] teleop ENGAGING → ENABLED'",
        "plugin-rule": "'tip left its sphere'",
    }
    for name, until in cases.items():
        (line,) = commands(name)
        work = tmp_path / name
        work.mkdir()
        r = in_netns(PLUGIN_SCRIPT.format(root=ROOT, up=line, until=until), work, 130)
        log = (work / "up.log").read_text()
        assert "up exit 0" in r.stdout, f"{name}: {r.stdout}{r.stderr}\n{log[-4000:]}"
        assert until.strip("'") in log, f"{name}:\n{log[-4000:]}"
        assert not stop_errors(log), f"{name}: an orderly stop logged errors:\n" + "\n".join(stop_errors(log))
        if name == "plugin-robot":
            assert re.search(r"mapping \S+ → arm1 \(reach\)", log), log[-3000:]


# ------------------------------------------------------------- learning.md: robot learning


@pytest.mark.process
@pytest.mark.timeout(1500)  # (the first run makes LeRobot's reader venv: torch, up to 20 min)
def test_recording_to_dataset_to_a_policy_run_as_written(tmp_path: Path) -> None:
    """docs/learning.md: a site with two clutch presses (and its camera) recorded, exported as a
    LeRobotDataset and read back by LeRobot's own reader, pyarrow and PyAV
    (tests/lerobot_check.py); then the dataset's first episode, as a policy, drives a fresh site:
    its slave follows the policy and moves."""
    from lerobot_check import check_dataset
    from telesurg.services.record import iter_decoded, open_mcap
    from telesurg.shared.messages import CartesianPose, OperatingState

    record, export, policy = commands("learning")
    script = f"""
{record} > record.log 2>&1
echo "record exit $?"
{export} > export.log 2>&1
echo "export exit $?"
{policy} > policy.log 2>&1
echo "policy exit $?"
"""
    r = in_netns(script, tmp_path, 400)
    logs = {
        n: (tmp_path / f"{n}.log").read_text()
        for n in ("record", "export", "policy")
        if (tmp_path / f"{n}.log").exists()
    }
    for n in ("record", "export", "policy"):
        assert f"{n} exit 0" in r.stdout, f"{r.stdout}{r.stderr}\n{logs.get(n, '')[-4000:]}"
    print(logs["export"].strip().splitlines()[-1])
    figures = check_dataset(tmp_path / "run.mcap", tmp_path / "dataset", 10.0)
    print(figures)
    assert not stop_errors(logs["policy"]), "\n".join(stop_errors(logs["policy"]))
    assert "policy telesurg.gym.policies:replay at 30 Hz" in logs["policy"], logs["policy"][-3000:]
    follow, tips = False, []
    with open_mcap(tmp_path / "policy.mcap") as reader:
        for topic, _lt, _pt, _d, msg in iter_decoded(reader, lambda t: "/slave/arm1/" in t):
            if isinstance(msg, OperatingState) and msg.header.source == "slave_control":
                follow = msg.follow
            elif follow and isinstance(msg, CartesianPose) and topic.endswith("/measured_cp"):
                tips.append(msg.position)
    assert tips, "the slave never followed the policy"
    travel = float(np.max(np.linalg.norm(np.array(tips) - tips[0], axis=1)))
    from telesurg.gym.policies import episode_targets

    targets, _fps = episode_targets(tmp_path / "dataset", 0)
    recorded = float(np.max(np.linalg.norm(targets - targets[0], axis=1)))
    print(
        f"policy run: the slave followed the replayed episode, its tip moved up to {travel * 1e3:.1f} mm "
        f"(the episode's target {recorded * 1e3:.1f} mm)"
    )
    assert travel > 0.5 * recorded > 5e-3


# --------------------------------------------------------------------------- messages.md


@pytest.mark.process
@pytest.mark.timeout(120)
def test_the_messages_examples_as_written(tmp_path: Path) -> None:
    """docs/messages.md §4: the Node example against a router (the one the page names), and the
    encode / decode example."""
    lang, node = recipe("messages-node")
    assert lang == "python"
    (tmp_path / "node_example.py").write_text("\n".join(node) + "\n")
    lang, codec = recipe("messages-codec")
    assert lang == "python"
    (tmp_path / "codec_example.py").write_text("\n".join(codec) + "\n")
    script = f"""
telesurg router --listen tcp/127.0.0.1:7447 > router.log 2>&1 &
R=$!
for i in $(seq 150); do (echo > /dev/tcp/127.0.0.1/7447) 2>/dev/null && break; sleep 0.2; done
"{sys.executable}" node_example.py
echo "node exit $?"
"{sys.executable}" codec_example.py
echo "codec exit $?"
kill -INT $R; wait $R
"""
    r = in_netns(script, tmp_path, 110)
    print(r.stdout)
    assert "node exit 0" in r.stdout and "codec exit 0" in r.stdout, r.stdout + r.stderr
    assert "telesurg/scratch/slave/arm1/servo_jp example 0 False (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)" in r.stdout
    assert "{'received': 1, 'gaps': 0, 'lost': 0" in r.stdout
    assert "not a valid MessagePack payload" in r.stdout


# --------------------------------------------------------------------------- the first hour


def test_version_comes_from_the_package_metadata() -> None:
    out = subprocess.run([str(BIN / "telesurg"), "--version"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == f"telesurg {version('telesurg')}", out


@pytest.mark.process
@pytest.mark.timeout(120)
def test_commands_without_a_site_say_what_to_do(tmp_path: Path) -> None:
    """No router on the default port: one line naming it and what to do, a non-zero exit."""
    script = """
telesurg keys init "$XDG_STATE_HOME/telesurg/local/keys" > /dev/null
telesurg record --out run.mcap --seconds 2 2> record.err; echo "record exit $?"
telesurg estop 2> estop.err; echo "estop exit $?"
telesurg cmd begin_posture_adjust method=ptp --yes 2> cmd.err; echo "cmd exit $?"
"""
    r = in_netns(script, tmp_path, 110)
    for name in ("record", "estop", "cmd"):
        assert re.search(rf"{name} exit [12]\b", r.stdout), r.stdout
        err = (tmp_path / f"{name}.err").read_text().strip()
        assert len(err.splitlines()) == 1, err
        assert "no router at tcp/127.0.0.1:7447: start a site with `telesurg up`, or pass --connect" in err
        assert ".rs:" not in err, err


def test_console_sh_without_a_keyring_says_what_to_do(tmp_path: Path) -> None:
    subprocess.run(
        [str(BIN / "telesurg"), "certs", "--out", str(tmp_path / "certs")],
        check=True,
        capture_output=True,
        timeout=60,
    )
    env = dict(os.environ, XDG_STATE_HOME=str(tmp_path / "state"), HOME=str(tmp_path))
    env.pop("TELESURG_KEYS", None)
    out = subprocess.run(
        ["bash", str(ROOT / "deploy" / "console.sh"), "127.0.0.1", "--certs", str(tmp_path / "certs")],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert f"no keyring at {tmp_path / 'state' / 'telesurg' / 'lab' / 'keys'}" in out.stderr
    assert "telesurg keys export master_capture console --to console --site lab" in out.stderr
