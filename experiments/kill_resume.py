"""kill -9 at random moments of a training run: every resume ends at bit-identical parameters.

The crash-safety check of training, as a script (minutes on a CPU, so not part of `make test`;
tests/test_train_loop.py has the one-kill version):

1. `scenegen prepare` a tiny-config cache of the Argoverse 2 train logs into a temporary folder;
2. `scenegen train` an uninterrupted run of `--steps` steps (a small model via `--set`, of
   tests/small.py's width with more actor slots; a checkpoint every `--save-every` steps);
3. the same command in a second workdir, killed with SIGKILL `--kills` times at seeded random
   moments and restarted after each kill, then run to completion;
4. the final train states of both runs compared leaf by leaf with `np.array_equal`.

Each kill aims at a phase drawn at random: "startup" (a delay within the time the uninterrupted
run took to log its first step: imports, restoring the checkpoint, compiling, the first step),
"training" (a delay of up to two save intervals after the restarted run logged its first step)
or "saving" (as soon as an unfinished orbax checkpoint folder appears). The phase the process
was found in at the kill is recorded as well. The persistent compile cache is off for every run
(unless `--compile-cache`), so each restart compiles again and startup kills land mid-compile.

Prints a JSON summary (also written to `--out`): per kill the aim, the delay, the phase found,
the step the next run resumed from; whether the final parameters and the whole train state are
bit-identical; whether metrics.jsonl has one row per step. Exits 1 unless all hold.

  python experiments/kill_resume.py --kills 20 --seed 0 --out /tmp/kill_resume.json
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEFAULT_DATA = os.path.normpath(os.path.join(REPO, "..", "shared", "data", "av2_sensor_mini"))
# tests/small.py's width, more actor slots: a step takes a fraction of a second on one core.
SMALL = ("max_actors=15", "bptt_window=8", "batch_size=2", "hidden=8", "gn_groups=2")
TMP_MARKER = ".orbax-checkpoint-tmp"  # orbax's name for a checkpoint folder being written
CHECKSUM_FILE = "scenegen_sha256.json"  # written last into a saved step's folder
AIMS = ("startup", "training", "saving")
POLL_S = 0.01
RUN_TIMEOUT_S = 3600.0


def scenegen() -> list[str]:
    """The `scenegen` command of this Python environment."""
    script = os.path.join(os.path.dirname(sys.executable), "scenegen")
    if os.path.isfile(script):
        return [script]
    return [sys.executable, "-c", "import sys; from scenegen_jax.cli import main; sys.exit(main())"]


def saved_steps(workdir: str) -> list[int]:
    ckpts = os.path.join(workdir, "checkpoints")
    if not os.path.isdir(ckpts):
        return []
    return sorted(int(d) for d in os.listdir(ckpts) if d.isdigit())


def unfinished(workdir: str) -> set[str]:
    """Checkpoint folders being written: orbax temporaries, and step folders without their
    checksums (written last)."""
    ckpts = os.path.join(workdir, "checkpoints")
    try:
        names = os.listdir(ckpts)
    except FileNotFoundError:
        return set()
    return {n for n in names if TMP_MARKER in n or (n.isdigit() and not os.path.exists(
        os.path.join(ckpts, n, CHECKSUM_FILE)))}


def saving(workdir: str, old: set[str]) -> bool:
    """Whether a save is under way: an unfinished folder other than the `old` ones (left by
    the previous kill)."""
    return bool(unfinished(workdir) - old)


def logged_steps(workdir: str) -> list[int]:
    """Steps in metrics.jsonl (rows cut short by a kill are skipped)."""
    path = os.path.join(workdir, "metrics.jsonl")
    if not os.path.isfile(path):
        return []
    out = []
    with open(path) as f:
        for line in f:
            try:
                out.append(int(json.loads(line)["step"]))
            except (ValueError, KeyError, TypeError):
                pass
    return out


def newest_logged(workdir: str, since: float) -> int | None:
    """The last step logged after time `since` (s, epoch), if any."""
    path = os.path.join(workdir, "metrics.jsonl")
    try:
        if os.path.getmtime(path) < since:
            return None
    except FileNotFoundError:
        return None
    steps = logged_steps(workdir)
    return steps[-1] if steps else None


def run_cmd(data: str, workdir: str, args: argparse.Namespace) -> list[str]:
    return [
        *scenegen(), "train", "--config", "tiny", "--data", data, "--workdir", workdir,
        "--steps", str(args.steps), "--save-every", str(args.save_every), "--log-every", "1",
        "--keep", "3", "--set", *SMALL, f"seed={args.seed}",
    ]  # fmt: skip


def launch(cmd: list[str], log_path: str, env: dict) -> subprocess.Popen:
    with open(log_path, "w") as log:  # the child keeps its own descriptor
        return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)


def wait_until(proc: subprocess.Popen, ready, timeout_s: float = RUN_TIMEOUT_S) -> bool:
    """Polls until `ready()` (True) or the process exits (False)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            return False
        if ready():
            return True
        time.sleep(POLL_S)
    raise TimeoutError(f"{proc.args}: no progress in {timeout_s} s")


def check_exit(proc: subprocess.Popen, log_path: str) -> None:
    if proc.returncode != 0:
        with open(log_path) as f:
            tail = f.read()[-3000:]
        raise RuntimeError(f"{' '.join(proc.args)} exited with {proc.returncode}:\n{tail}")


def run_log_facts(log_path: str, on_disk: int) -> dict:
    """What a run's log says about its start: the step it resumed from (0: no checkpoint on
    disk, a fresh start; None: killed before it restored one), damaged checkpoints set aside,
    unfinished saves removed."""
    with open(log_path, errors="replace") as f:
        text = f.read()
    restored = re.findall(r"restored the checkpoint of step (\d+)", text)
    return {
        "resumed_from": int(restored[-1]) if restored else (0 if on_disk == 0 else None),
        "set_aside": text.count("damaged checkpoint moved to"),
        "unfinished_saves_removed": text.count("removing an unfinished save"),
    }


def uninterrupted(cmd: list[str], workdir: str, log_path: str, env: dict) -> dict:
    """Runs `cmd` to completion; times to the first logged step and to the end, s."""
    start, t0 = time.time(), time.monotonic()
    proc = launch(cmd, log_path, env)
    wait_until(proc, lambda: newest_logged(workdir, start) is not None)
    first = time.monotonic() - t0
    proc.wait(RUN_TIMEOUT_S)
    check_exit(proc, log_path)
    return {"first_step_s": first, "total_s": time.monotonic() - t0}


def killed_run(
    cmd: list[str], workdir: str, logs: str, env: dict, args: argparse.Namespace, timing: dict
) -> list[dict]:
    """Runs `cmd` with `args.kills` kills at seeded random moments, then to completion."""
    rng = np.random.default_rng(args.seed)
    step_s = (timing["total_s"] - timing["first_step_s"]) / max(args.steps - 1, 1)
    kills: list[dict] = []
    for k in range(args.kills + 1):
        log_path = os.path.join(logs, f"run{k:02d}.log")
        on_disk = (saved_steps(workdir) or [0])[-1]
        old = unfinished(workdir)
        start, t0 = time.time(), time.monotonic()
        proc = launch(cmd, log_path, env)
        if k == args.kills:  # the last run goes to the end
            proc.wait(RUN_TIMEOUT_S)
            check_exit(proc, log_path)
            if kills:
                kills[-1]["next_run"] = run_log_facts(log_path, on_disk)
            break
        aim = str(rng.choice(AIMS))
        if aim == "startup":
            delay = float(rng.uniform(0.0, timing["first_step_s"]))
            alive = wait_until(proc, lambda: time.monotonic() - t0 >= delay)  # noqa: B023
        elif aim == "training":
            delay = float(rng.uniform(0.0, 2 * args.save_every * step_s))
            alive = wait_until(
                proc,
                lambda: (newest_logged(workdir, start) or 0) > on_disk,  # noqa: B023
            )
            t1 = time.monotonic()
            alive = alive and wait_until(proc, lambda: time.monotonic() - t1 >= delay)  # noqa: B023
        else:
            delay = None
            alive = wait_until(proc, lambda: saving(workdir, old))  # noqa: B023
        found = (
            "saving" if saving(workdir, old)
            else "training" if (newest_logged(workdir, start) or 0) > on_disk
            else "startup"
        )  # fmt: skip
        if alive:
            os.kill(proc.pid, signal.SIGKILL)
        proc.wait(RUN_TIMEOUT_S)
        if kills:
            kills[-1]["next_run"] = run_log_facts(log_path, on_disk)
        if proc.returncode != -signal.SIGKILL:
            check_exit(proc, log_path)  # a crash raises; a finished run ends the kills
            kills.append({"aim": aim, "finished_before_the_kill": True})
            break
        kills.append({
            "aim": aim,
            "delay_s": None if delay is None else round(delay, 3),
            "at_s": round(time.monotonic() - t0, 3),
            "found": found,
            "checkpoint_on_disk_at_start": on_disk,
            "logged_step_at_kill": newest_logged(workdir, start),
            "checkpoints_after": saved_steps(workdir),
        })  # fmt: skip
        print(f"kill {len(kills)}/{args.kills}: {json.dumps(kills[-1])}", file=sys.stderr)
    return kills


def compare(workdir_a: str, workdir_b: str) -> dict:
    """Leaf-by-leaf bit equality of two workdirs' newest train states."""
    import jax

    from scenegen_jax.train.loop import load_trained

    (_, a), (_, b) = load_trained(workdir_a), load_trained(workdir_b)
    leaves_a = jax.tree_util.tree_flatten_with_path(jax.device_get(a._asdict()))[0]
    leaves_b = jax.tree_util.tree_flatten_with_path(jax.device_get(b._asdict()))[0]
    if [p for p, _ in leaves_a] != [p for p, _ in leaves_b]:
        return {"same_structure": False}
    differ = [
        jax.tree_util.keystr(p)
        for (p, x), (_, y) in zip(leaves_a, leaves_b, strict=True)
        if not (np.asarray(x).dtype == np.asarray(y).dtype and np.array_equal(x, y))
    ]
    params = [d for d in differ if d.startswith("['params']")]
    n_params = sum(jax.tree_util.keystr(p).startswith("['params']") for p, _ in leaves_a)
    return {
        "final_steps": [int(a.step), int(b.step)],
        "param_leaves": n_params,
        "state_leaves": len(leaves_a),
        "params_identical": not params,
        "state_identical": not differ,
        "differing_leaves": differ[:20],
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--kills", type=int, default=20)
    p.add_argument("--steps", type=int,
                   help="training steps (default: enough that the kills cannot finish the run, "
                   "2 * save_every * (kills + 2))")
    p.add_argument("--save-every", type=int, default=2)
    p.add_argument("--seed", type=int, default=0, help="kill moments and the model's seed")
    p.add_argument("--data", default=DEFAULT_DATA, help="Argoverse 2 root (holds train/)")
    p.add_argument("--out", help="also write the JSON summary here")
    p.add_argument("--compile-cache", action="store_true",
                   help="keep JAX's persistent compile cache (restarts then skip compiling)")
    p.add_argument("--keep", action="store_true", help="keep the temporary folder")
    args = p.parse_args(argv)
    if args.kills < 0 or args.save_every < 1:
        p.error("--kills must be >= 0 and --save-every >= 1")
    args.steps = args.steps or 2 * args.save_every * (args.kills + 2)

    env = {**os.environ, "JAX_PLATFORMS": os.environ.get("JAX_PLATFORMS", "cpu")}
    if not args.compile_cache:
        env["SCENEGEN_COMPILE_CACHE"] = "off"
    root = tempfile.mkdtemp(prefix="kill_resume_")
    t_start = time.monotonic()
    try:
        cache, full, killed = (os.path.join(root, n) for n in ("cache", "full", "killed"))
        logs = os.path.join(root, "logs")
        os.makedirs(logs)
        subprocess.run(
            [*scenegen(), "prepare", "--root", args.data, "--split", "train", "--out", cache,
             "--config", "tiny", "--workers", "1"],
            check=True, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        timing = uninterrupted(run_cmd(cache, full, args), full, os.path.join(logs, "full.log"),
                               env)
        print(f"uninterrupted: {json.dumps(timing)}", file=sys.stderr)
        kills = killed_run(run_cmd(cache, killed, args), killed, logs, env, args, timing)
        result = compare(full, killed)
        rows = logged_steps(killed)
        done = [k for k in kills if not k.get("finished_before_the_kill")]
        summary = {
            "kills": len(done),
            "kills_asked": args.kills,
            "steps": args.steps,
            "save_every": args.save_every,
            "seed": args.seed,
            "uninterrupted": {k: round(v, 2) for k, v in timing.items()},
            "found_at_kill": {ph: sum(k["found"] == ph for k in done) for ph in AIMS},
            "resumed_from": [k.get("next_run", {}).get("resumed_from") for k in done],
            "per_kill": kills,
            **result,
            "identical": bool(result.get("params_identical") and result.get("state_identical")),
            "metrics_one_row_per_step": rows == list(range(1, args.steps + 1)),
            "wall_s": round(time.monotonic() - t_start, 1),
            "tmp": root if args.keep else None,
        }
    finally:
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)
    text = json.dumps(summary, indent=1)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")
    ok = summary["identical"] and summary["metrics_one_row_per_step"]
    return 0 if ok and summary["kills"] == args.kills else 1


if __name__ == "__main__":
    sys.exit(main())
