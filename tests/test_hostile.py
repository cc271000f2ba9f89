"""Hostile inputs at every ``epo`` subcommand: each is refused in one line, never a traceback.

The suite walks the command table itself (:data:`scenarios.cli.COMMANDS` and the groups'
subcommands), so a new command or option is covered without editing this file:

- every integer and float option gets ``nan``, ``inf``, a 23-digit integer and a word;
- every command that reads a file or folder gets a missing path, a folder for a file (or a
  file for a folder), an empty file and random bytes, on a base invocation that is valid
  otherwise;
- every command that writes gets an output path through an existing file;
- every ``--set`` gets a text without ``=``, an unreadable list and an unknown key.

Each case must exit with status 2 and print exactly one ``error:`` line (an uncaught
exception escapes :func:`scenarios.cli.main` and fails the test). A case that starts real
work instead of refusing is stopped by an alarm and fails. ``bench/hostile.py`` runs the
longer version (more values per class, and every case in a fresh process).
"""

from __future__ import annotations

import os
import shutil
import signal
from pathlib import Path

import click
import pytest

from scenarios.cli import COMMANDS, cli
from tests.helpers import one_error_line

ROOT = Path(__file__).resolve().parents[1]
GAME = ROOT / "scenarios" / "examples" / "crossing2.yaml"
#: seconds a refused case may take (imports included); more means the command ran
ALARM = 90


def leaf_commands() -> list[tuple[tuple[str, ...], click.Command]]:
    """Every runnable ``epo`` command as (its words, the click command)."""
    out = []

    def walk(words, cmd):
        if isinstance(cmd, click.Group):
            for name in cmd.list_commands(None):
                walk((*words, name), cmd.get_command(None, name))
        else:
            out.append((words, cmd))

    for name in sorted(COMMANDS):
        walk((name,), cli.get_command(None, name))
    return out


LEAVES = leaf_commands()

#: values that no number option may accept, by the option's type
BAD_FLOATS = ("nan", "inf", "-inf", "1e999", "abc")
BAD_INTS = ("99999999999999999999999", "-99999999999999999999999", "1.5", "abc")


def number_cases():
    for words, cmd in LEAVES:
        for p in cmd.params:
            if not isinstance(p, click.Option) or p.is_flag:
                continue
            if isinstance(p.type, click.types.FloatParamType):
                values = BAD_FLOATS
            elif isinstance(p.type, click.types.IntParamType):
                values = BAD_INTS
            else:
                continue
            for v in values:
                yield pytest.param(words, p.opts[0], v, id=f"{' '.join(words)} {p.opts[0]}={v}")


class _Ran(Exception):
    pass


def run_refused(capsys, args, *words) -> str:
    """``epo ARGS`` in-process under an alarm; asserts one error line; returns it."""
    from scenarios.cli import main

    def alarm(signum, frame):
        raise _Ran(f"epo {' '.join(map(str, args))} ran for {ALARM} s instead of refusing")

    old = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(ALARM)
    try:
        rc = main([str(a) for a in args])
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    _, err = capsys.readouterr()
    return one_error_line(rc, err, *words)


def test_the_walk_sees_every_command():
    """The table below must name a base invocation for every command the CLI has."""
    assert {" ".join(w) for w, _ in LEAVES} == set(BASES), "add the new command to BASES"


@pytest.mark.parametrize(("words", "option", "value"), list(number_cases()))
def test_number_options_refuse_non_finite_huge_and_words(capsys, words, option, value):
    # the hostile option first: click checks options in the order they were given
    run_refused(capsys, [*words, option, value], option)


# ---- files and folders --------------------------------------------------------------------
@pytest.fixture(scope="module")
def world(tmp_path_factory):
    return make_world(tmp_path_factory.mktemp("hostile"))


def make_world(root: Path) -> dict[str, Path]:
    """A tiny dataset, a one-epoch run on it, a game file, one exiD-layout recording and
    hostile files beside them, under ``root``; the paths by name."""
    from learning.models import ModelConfig
    from learning.train import TrainConfig, train
    from scenarios.cli import main
    from tests.test_models import TINY, synthetic_dataset

    data = synthetic_dataset()
    run = root / "run"
    cfg = TrainConfig(model=ModelConfig(kind="sc", **TINY), epochs=1, batch_size=4, seed=0)
    train(data, run, cfg, progress=False)
    (root / "empty.yaml").write_text("")
    (root / "garbage.bin").write_bytes(os.urandom(4096))
    (root / "a_file").write_text("not a folder\n")
    (root / "empty_dir").mkdir()
    garbage_dir = root / "garbage_dir"  # a folder whose manifest/config/CSV files are noise
    garbage_dir.mkdir()
    for name in ("manifest.json", "config.json", "recordingMeta.csv", "00_tracks.csv"):
        (garbage_dir / name).write_bytes(os.urandom(512))
    (root / "dangling").symlink_to(root / "nowhere")
    os.mkfifo(root / "fifo")  # reading a pipe blocks: readers must refuse non-regular files
    fifo_dir = root / "fifo_dir"  # a folder whose metadata files are pipes
    fifo_dir.mkdir()
    for name in ("manifest.json", "config.json", "00_recordingMeta.csv", "00_tracks.csv"):
        os.mkfifo(fifo_dir / name)
    exid_raw = root / "exid_raw"  # one short generated recording in the exiD layout
    args = ["generate", "highway-raw", "--out", exid_raw, "--recordings", "1", "--duration", "24"]
    args += ["--no-progress", "--set", "warmup=20", "--set", "frame_rate=10"]
    assert main([str(a) for a in args]) == 0
    vci_raw = root / "vci_raw"  # one clip of the CITR layout: a cart and a pedestrian
    vci_raw.mkdir()
    rows = [f"1,{f},ped,{0.1 * f},1.0,3.0,0.0" for f in range(60)]
    (vci_raw / "c_01_traj_ped_filtered.csv").write_text(
        "\n".join(["id,frame,label,x_est,y_est,vx_est,vy_est", *rows]) + "\n"
    )
    rows = [f"1,{f},veh,{0.05 * f},0.0,0.0,1.5" for f in range(60)]
    (vci_raw / "c_01_traj_veh_filtered.csv").write_text(
        "\n".join(["id,frame,label,x_est,y_est,psi_est,vel_est", *rows]) + "\n"
    )
    eth_ucy_raw = root / "eth_ucy_raw"  # two small ETH/UCY files: a test and a training scene
    eth_ucy_raw.mkdir()
    eth_rows = "".join(f"{10 * k}\t{p}\t{0.4 * k}\t{2.0 * p}\n" for k in range(30) for p in (1, 2))
    for name in ("biwi_eth.txt", "biwi_hotel.txt"):
        (eth_ucy_raw / name).write_text(eth_rows)
    from tests.test_real_waymo import write_tiny  # two small Waymo scenarios, one pair each

    waymo_raw = write_tiny(root / "waymo_raw" / "t.tfrecord")
    return {
        "exid_raw": exid_raw,
        "eth_ucy_raw": eth_ucy_raw,
        "waymo_raw": waymo_raw,
        "vci_raw": vci_raw,
        "root": root,
        "data": data,
        "run": run,
        "game": GAME,
        "missing": root / "missing" / "thing",
        "empty": root / "empty.yaml",
        "garbage": root / "garbage.bin",
        "file": root / "a_file",
        "empty_dir": root / "empty_dir",
        "garbage_dir": root / "garbage_dir",
        "dangling": root / "dangling",
        "fifo": root / "fifo",
        "fifo_dir": fifo_dir,
        "device": Path("/dev/zero"),  # endless: a reader must not read it whole
        "through_file": root / "a_file" / "out",
    }


#: per command: its arguments with ``{slot}`` placeholders filled from ``world``; ``IN`` is
#: the input slot the file cases replace, ``OUT`` the output the write cases replace
BASES: dict[str, dict] = {
    "solve": {"args": ["{IN}", "--out", "{OUT}/r.json"], "in": "file", "out": "file"},
    "inspect": {"args": ["{IN}", "--plot", "{OUT}/p.png"], "in": "file", "out": "file"},
    "export": {
        "args": ["{IN}", "--format", "casadi", "--out", "{OUT}"],
        "in": "file",
        "out": "dir",
    },
    "compare": {"args": ["{IN}", "--quick", "--no-figures", "--out", "{OUT}"], "in": "file"},
    "demo": {"args": ["--out", "{OUT}"], "out": "dir"},
    "data show": {"args": ["{IN}", "--index", "0"], "in": "data"},
    "data verify": {"args": ["{IN}"], "in": "data"},
    "evaluate": {"args": ["{RUN}", "--data", "{IN}", "--out", "{OUT}"], "in": "data", "out": "dir"},
    "show-predictions": {"args": ["{RUN}", "--data", "{IN}", "--out", "{OUT}/f.png"], "in": "data"},
    "show-weights": {"args": ["{RUN}", "--data", "{IN}", "--out", "{OUT}/f.png"], "in": "data"},
    "train": {
        "args": ["--data", "{IN}", "--out", "{OUT}", "--epochs", "1", "--model", "sc"],
        "in": "data",
        "out": "dir",
    },
    "generate exid": {"args": ["--raw", "{IN}", "--out", "{OUT}"], "in": "exid", "out": "dir"},
    "generate eth-ucy": {
        "args": ["--raw", "{IN}", "--out", "{OUT}"],
        "in": "eth_ucy",
        "out": "dir",
    },
    "generate vci": {"args": ["--raw", "{IN}", "--out", "{OUT}"], "in": "vci", "out": "dir"},
    "generate waymo": {"args": ["--raw", "{IN}", "--out", "{OUT}"], "in": "waymo", "out": "dir"},
    "generate rpi": {"args": ["--samples", "4", "--out", "{OUT}"], "out": "dir"},
    "generate left-turn": {
        "args": ["--episodes-per-geometry", "1", "--out", "{OUT}"],
        "out": "dir",
    },
    "generate highway-raw": {"args": ["--recordings", "1", "--out", "{OUT}"], "out": "dir"},
    "simulate": {"args": ["left-turn", "--episodes", "1", "--out", "{OUT}"], "out": "dir"},
    "pipeline": {"args": ["--samples", "4", "--out", "{OUT}"], "out": "dir"},
}

#: the input cases: the slot's replacement, by the kind of input
IN_CASES = {
    "file": ("missing", "empty", "garbage", "empty_dir", "dangling", "fifo", "device"),
    "data": ("missing", "file", "empty_dir", "garbage_dir", "garbage", "dangling", "fifo_dir"),
}
IN_CASES["exid"] = IN_CASES["data"]
IN_CASES["eth_ucy"] = IN_CASES["data"]
IN_CASES["vci"] = IN_CASES["data"]
IN_CASES["waymo"] = IN_CASES["file"]


def _fill(base: dict, world: dict, tmp_path: Path, IN=None, OUT=None) -> list[str]:
    good_in = {"file": world["game"], "data": world["data"], "exid": world["exid_raw"]}
    good_in["eth_ucy"] = world["eth_ucy_raw"]
    good_in["vci"] = world["vci_raw"]
    good_in["waymo"] = world["waymo_raw"]
    good_in = good_in.get(base.get("in"))
    out = OUT if OUT is not None else tmp_path / "out"
    subs = {"{IN}": IN if IN is not None else good_in, "{OUT}": out, "{RUN}": world["run"]}
    args = []
    for a in base["args"]:
        for k, v in subs.items():
            a = a.replace(k, str(v))
        args.append(a)
    return args


def input_cases():
    for cmd, base in BASES.items():
        for case in IN_CASES.get(base.get("in"), ()):
            yield pytest.param(cmd, case, id=f"{cmd} <- {case}")


@pytest.mark.parametrize(("cmd", "case"), list(input_cases()))
def test_bad_inputs_are_one_line(capsys, world, tmp_path, cmd, case):
    args = _fill(BASES[cmd], world, tmp_path, IN=world[case])
    run_refused(capsys, [*cmd.split(), *args])


def output_cases():
    for cmd, base in BASES.items():
        if "out" in base:
            for case in ("through_file",) + (("file",) if base["out"] == "dir" else ()):
                yield pytest.param(cmd, case, id=f"{cmd} -> {case}")


@pytest.mark.parametrize(("cmd", "case"), list(output_cases()))
def test_unwritable_outputs_are_one_line(capsys, world, tmp_path, cmd, case):
    args = _fill(BASES[cmd], world, tmp_path, OUT=world[case])
    run_refused(capsys, [*cmd.split(), *args])


#: as root, permissions are dropped for the read-only cases (root writes anywhere)
SETPRIV = shutil.which("setpriv")
DROP = [
    "--inh-caps=-dac_override,-dac_read_search",
    "--bounding-set=-dac_override,-dac_read_search",
]


@pytest.mark.skipif(
    os.geteuid() == 0 and SETPRIV is None, reason="root writes into read-only folders"
)
@pytest.mark.parametrize("cmd", [c for c, b in BASES.items() if b.get("out") == "dir"])
def test_read_only_output_folders_are_one_line(capsys, world, tmp_path, cmd):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        args = [*cmd.split(), *_fill(BASES[cmd], world, tmp_path, OUT=ro / "out")]
        if os.geteuid() != 0:
            run_refused(capsys, args)
            return
        import subprocess
        import sys

        r = subprocess.run(
            [SETPRIV, *DROP, "--", sys.executable, "-m", "scenarios.cli", *map(str, args)],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=ALARM * 2,
        )
        one_error_line(r.returncode, r.stderr)
    finally:
        ro.chmod(0o700)
        shutil.rmtree(ro, ignore_errors=True)


# ---- KEY=VALUE -----------------------------------------------------------------------------
def set_cases():
    for words, cmd in LEAVES:
        if any(isinstance(p, click.Option) and "--set" in p.opts for p in cmd.params):
            cmd_name = " ".join(words)
            for text in ("noequals", "x=[1, 2", "no_such_key_at_all=1"):
                yield pytest.param(cmd_name, text, id=f"{cmd_name} --set {text}")


@pytest.mark.parametrize(("cmd", "text"), list(set_cases()))
def test_bad_settings_are_one_line(capsys, world, tmp_path, cmd, text):
    args = _fill(BASES[cmd], world, tmp_path)
    line = run_refused(capsys, [*cmd.split(), "--set", text, *args])
    if text.startswith("no_such"):
        assert "no_such_key_at_all" in line, line
