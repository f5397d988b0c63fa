"""What several subcommands share: `--set FIELD=VALUE` overrides, and the model of
`--pretrained NAME|DIR` or `--workdir` (`--step`)."""

from __future__ import annotations


def overrides(pairs: list[str]) -> dict[str, str]:
    """{field: value} of `--set FIELD=VALUE ...` (values still strings)."""
    out = {}
    for pair in pairs or []:
        if "=" not in pair:
            raise SystemExit(f"override {pair!r} must look like field=value")
        k, v = pair.split("=", 1)
        out[k] = v
    return out


def load_model(args):
    """(config, parameters, training step) of `--pretrained NAME` or `--workdir` (`--step`)."""
    import jax

    if args.pretrained:
        if args.step is not None:
            raise SystemExit("--step selects a checkpoint of --workdir; a pretrained model has one")
        from scenegen_jax.pretrained import load_pretrained

        cfg, params, manifest = load_pretrained(args.pretrained)
        step = manifest["step"]
    else:
        from scenegen_jax.workdir import load_params

        cfg, params, step = load_params(args.workdir, args.step)
    # Uncommitted copies: restored arrays are committed to a device, and jit compiles a
    # separate executable for committed inputs.
    return cfg, jax.device_put(jax.device_get(params)), step


def add_model_args(sp) -> None:
    """`--workdir DIR [--step N]` or `--pretrained NAME`: the model a command uses."""
    which = sp.add_mutually_exclusive_group(required=True)
    which.add_argument("--workdir", help="training workdir (config + checkpoints)")
    which.add_argument(
        "--pretrained", metavar="NAME",
        help="a model shipped with the package (`scenegen models` lists them) or a directory "
        "written by `scenegen export-model`",
    )
    sp.add_argument("--step", type=int, help="checkpoint step of --workdir (default: the latest)")
