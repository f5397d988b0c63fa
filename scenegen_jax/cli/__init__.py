"""The `scenegen` command line: one entry point with subcommands (one module per group)."""

from __future__ import annotations

import argparse
import logging
import os
import sys

from scenegen_jax import signals
from scenegen_jax.allocator import reexec_with_tcmalloc


def build_parser() -> argparse.ArgumentParser:
    # The subcommands' modules (numpy and more) load here, not with this package: the
    # command starts itself again on tcmalloc (`main`) before it loads them.
    from scenegen_jax.cli import data, model, sample, score

    p = argparse.ArgumentParser(prog="scenegen", description=__doc__)
    p.add_argument(
        "-v", "--verbose", action="store_true", help="debug logging; tracebacks with errors"
    )
    sub = p.add_subparsers(dest="command", required=True)
    for module in (data, model, score, sample):
        module.add_parsers(sub)
    return p


COMPILE_CACHE_MAX_BYTES = 2 * 2**30


def enable_compile_cache() -> str | None:
    """Keeps compiled programs across runs in JAX's persistent compilation cache, so that a
    second `train`, `score`, `sample` or `evaluate` of the same shapes skips XLA's compilation
    (a large part of a run's start-up). The directory is JAX_COMPILATION_CACHE_DIR when
    set (with JAX's own size limit, JAX_COMPILATION_CACHE_MAX_SIZE), else
    $XDG_CACHE_HOME/scenegen_jax/jax (~/.cache by default), at most 2 GiB (least recently
    used entries go first); SCENEGEN_COMPILE_CACHE=off turns it off. Returns the directory.
    """
    import jax

    switch = os.environ.get("SCENEGEN_COMPILE_CACHE", "")
    if switch.lower() in ("0", "off", "false", "no"):
        return None
    if switch.lower() not in ("", "1", "on", "true", "yes"):
        raise ValueError(f"SCENEGEN_COMPILE_CACHE={switch}: use off (or 0, false, no) to turn "
                         "the compile cache off, on (or unset) to keep it")
    if not jax.config.jax_compilation_cache_dir:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache")
        jax.config.update("jax_compilation_cache_dir", os.path.join(base, "scenegen_jax", "jax"))
        jax.config.update("jax_compilation_cache_max_size", COMPILE_CACHE_MAX_BYTES)
    return jax.config.jax_compilation_cache_dir


def start_jax(backend: bool) -> None:
    """Sets JAX's process-wide switches as the package needs them and, with `backend`, starts
    JAX's backend, so that a JAX_PLATFORMS naming one this machine lacks is one line of
    error, not a traceback. Only the commands that compute with JAX start it (`prepare` on a
    GPU node takes no accelerator memory), and not a `--distributed` run: its backend starts
    when it joins the job (`jax.distributed.initialize` must come first)."""
    import jax

    # float32 throughout: JAX_ENABLE_X64=1 would make new arrays float64 and the convolutions
    # refuse the mix. numpy's broadcasting: JAX_NUMPY_RANK_PROMOTION=raise would refuse it.
    jax.config.update("jax_enable_x64", False)
    jax.config.update("jax_numpy_rank_promotion", "allow")
    if not backend:
        return
    try:
        jax.devices()
    except (RuntimeError, AssertionError) as e:  # AssertionError: a CUDA backend not built in
        reason = str(e).split("\n")[0] or "not available"
        raise ValueError(f"JAX_PLATFORMS={os.environ.get('JAX_PLATFORMS', '')}: JAX cannot "
                         f"start that backend here ({reason}); unset it to let JAX choose") from e


def main(argv: list[str] | None = None) -> None:
    if argv is None:  # the `scenegen` command itself: on tcmalloc where it is installed
        try:
            reexec_with_tcmalloc()
        except (FileNotFoundError, ValueError) as e:  # a bad SCENEGEN_MALLOC: exit 2
            print(f"scenegen: {e}", file=sys.stderr)
            raise SystemExit(2) from e
    previous = signals.install()  # first: a Ctrl-C during the imports below stops cleanly
    try:
        _run(argv)
    except KeyboardInterrupt as e:  # `signals.Stopped`: Ctrl-C or SIGTERM, at any moment
        raise _stopped(e) from None
    except Exception:
        # A stop that arrives while an extension module initialises comes back as that
        # module's ImportError ("initialization failed"): it is still the stop.
        stop = signals.pending_stop()
        if stop is None:
            raise
        raise _stopped(stop) from None
    finally:
        if argv is None:  # the command's work is done, its outputs whole
            signals.ignore_while_exiting()
        else:  # called inside another program (tests, scripts): its handlers back
            signals.restore(previous)


def _stopped(e: KeyboardInterrupt) -> SystemExit:
    """The exit of a command stopped by Ctrl-C or SIGTERM (`signals.Stopped`)."""
    logging.getLogger("scenegen").error("interrupted (%s)", e or "SIGINT")
    return SystemExit(getattr(e, "exit_status", 130))


def _run(argv: list[str] | None) -> None:
    args = build_parser().parse_args(argv)
    from scenegen_jax.cli import data, model, sample, score

    compiles = (model.cmd_train, model.cmd_reproduce, model.cmd_train_forecaster,
                model.cmd_train_baseline, score.cmd_score, sample.cmd_sample, score.cmd_evaluate)
    computes = (*compiles, model.cmd_models, model.cmd_export_model, data.cmd_render)

    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    for noisy in ("jax", "absl", "matplotlib", "orbax"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    try:
        start_jax(args.func in computes and not getattr(args, "distributed", False))
        if args.func in compiles:
            enable_compile_cache()
        args.func(args)
    except (OSError, ValueError, IndexError) as e:
        # Bad input (a file, a field, a flag): one line naming it, exit 2; -v adds the
        # traceback. Every reader raises these with the file and the field in the message.
        log = logging.getLogger("scenegen")
        log.error("%s", " ".join(str(e).split("\n")), exc_info=args.verbose)
        raise SystemExit(2) from e


if __name__ == "__main__":
    main()
