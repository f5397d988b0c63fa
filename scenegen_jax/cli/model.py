"""Models: `scenegen train`, `reproduce`, `export-model`, `train-forecaster` and `models` (the
other commands load a model with `common.load_model`, from `--pretrained` or `--workdir`)."""

from __future__ import annotations

import json

from scenegen_jax.cli.common import (
    add_distributed_args,
    nonnegative_int,
    overrides,
    path_arg,
    positive_float,
    positive_int,
    start_distributed,
)
from scenegen_jax.config import PRESETS, get_config


def cmd_train(args) -> None:
    from scenegen_jax.backend import is_main_process
    from scenegen_jax.train.loop import train

    cfg = get_config(args.config, **overrides(args.set))
    start_distributed(args)
    state = train(
        cfg,
        args.data,
        args.workdir,
        args.steps,
        save_every=args.save_every,
        log_every=args.log_every,
        keep=args.keep,
        max_seconds=args.minutes * 60 if args.minutes else None,
        init_from=args.init_from,
        weights=args.weights,
    )
    if is_main_process():
        print(json.dumps({"workdir": args.workdir, "step": int(state.step)}))


def cmd_reproduce(args) -> None:
    from scenegen_jax.backend import is_main_process
    from scenegen_jax.recipes import get_recipe
    from scenegen_jax.train.recipe import run_recipe

    recipe = get_recipe(args.recipe)
    done = run_recipe(recipe, args.workdir, args.cache_dir, args.data_root, runs=args.run,
                      out=args.out)
    if is_main_process():
        print(json.dumps({"recipe": recipe.name, "runs": done, "out": args.out}))


def cmd_export_model(args) -> None:
    from scenegen_jax.pretrained import save_pretrained
    from scenegen_jax.workdir import check_model_target, load_params

    check_model_target("--out", args.out)
    cfg, params, step = load_params(args.workdir, args.step)
    sampler = ({} if args.location_temperature is None
               else {"location_temperature": args.location_temperature})
    manifest = save_pretrained(args.out, cfg, params, step, args.workdir, sampler)
    print(json.dumps({"out": args.out, **manifest}))


def cmd_train_forecaster(args) -> None:
    from scenegen_jax.data.union import load_union
    from scenegen_jax.model.forecaster import ForecasterConfig
    from scenegen_jax.pretrained import resolve, save_companion
    from scenegen_jax.train.fit import save_run_config
    from scenegen_jax.train.forecaster import forecast_data, forecast_errors, train_forecaster

    out = resolve(args.out) if args.out else None  # a model to ship it with, checked first
    grid = get_config(args.config).grid
    cfg = ForecasterConfig(grid=grid)
    train = load_union(args.data, get_config(args.config))
    val = load_union(args.val_data, get_config(args.config))
    save_run_config(args.workdir, {
        "model": "forecaster", "config": args.config, **cfg.to_dict(), "data": args.data,
        "batch_size": args.batch_size, "lr": args.lr, "seed": args.seed})
    params = train_forecaster(cfg, forecast_data(train, grid, desc="draw train scenes"),
                              args.workdir, args.steps, args.batch_size, args.lr, args.seed)
    errors = forecast_errors(params, cfg, forecast_data(val, grid, desc="draw val scenes"))
    report = {"workdir": args.workdir, "step": args.steps, "val": errors}
    if out:
        save_companion(out, "forecaster", cfg, args.config, params, args.steps, args.workdir,
                       errors)
        report["out"] = out
    print(json.dumps(report))


def cmd_train_baseline(args) -> None:
    from scenegen_jax.data.union import load_union
    from scenegen_jax.eval.layout_vae import layout_vae_scores, summarize
    from scenegen_jax.likelihood.host_data import layout_data
    from scenegen_jax.model.layout_vae import LayoutVAEConfig
    from scenegen_jax.pretrained import resolve, save_companion
    from scenegen_jax.train.fit import save_run_config
    from scenegen_jax.train.layout_vae import train_layout_vae

    out = resolve(args.out) if args.out else None  # a model to ship it with, checked first
    cfg_grid = get_config(args.config)
    cfg = LayoutVAEConfig(grid=cfg_grid.grid)
    train = load_union(args.data, cfg_grid)
    val = load_union(args.val_data, cfg_grid)
    save_run_config(args.workdir, {
        "model": args.name, "config": args.config, **cfg.to_dict(), "data": args.data,
        "batch_size": args.batch_size, "lr": args.lr, "seed": args.seed})
    params = train_layout_vae(cfg, layout_data(train, cfg.grid, desc="draw train maps"),
                              args.workdir, args.steps, args.batch_size, args.lr, args.seed)
    figures = {"val_nll": summarize(layout_vae_scores(params, cfg, val, args.seed))}
    report = {"workdir": args.workdir, "step": args.steps, **figures}
    if out:
        save_companion(out, args.name, cfg, args.config, params, args.steps, args.workdir,
                       figures)
        report["out"] = out
    print(json.dumps(report))


def cmd_models(args) -> None:
    from scenegen_jax.pretrained import available, load_pretrained

    for name in available():
        cfg, _, manifest = load_pretrained(name)
        sampler = "".join(f", {k.replace('_', ' ')} {v}"
                          for k, v in manifest.get("sampler", {}).items())
        print(f"{name}\tconfig {cfg.name}, grid {cfg.grid.grid_size}, step {manifest['step']}, "
              f"{manifest['parameters']} parameters{sampler}")


def _add_companion_args(sp, grid: str, data: str, val: str, steps: int, folder: str) -> None:
    """The arguments of the commands that train a model shipped beside SceneGen."""
    sp.add_argument("--config", default="cpu", choices=sorted(PRESETS),
                    help=f"the preset whose grid it {grid}")
    sp.add_argument("--data", required=True, nargs="+", metavar="CACHE", help=data)
    sp.add_argument("--val-data", required=True, nargs="+", metavar="CACHE",
                    help=f"held-out caches for {val}")
    sp.add_argument("--workdir", required=True, type=path_arg,
                    help="checkpoints, run.json, metrics.jsonl (resumes)")
    sp.add_argument("--steps", type=nonnegative_int, default=steps)
    sp.add_argument("--batch-size", type=positive_int, default=32)
    sp.add_argument("--lr", type=positive_float, default=1e-3)
    sp.add_argument("--seed", type=nonnegative_int, default=0)
    sp.add_argument("--out", type=path_arg, help="the pretrained model (name or directory) to "
                    f"ship it with, in its {folder} folder")


def add_parsers(sub) -> None:
    """Registers this module's subcommands."""
    sp = sub.add_parser("train", help="train a model on a cache")
    sp.add_argument("--config", default="tiny", choices=sorted(PRESETS))
    sp.add_argument("--data", required=True, nargs="+", metavar="CACHE",
                    help="cache directories from `prepare` (same config, any sources), "
                    "trained on together")
    sp.add_argument("--weights", type=float, nargs="+", metavar="W",
                    help="one per --data cache: a scene comes from cache i with probability "
                    "W_i / sum(W) (default: the scene counts, uniform over all scenes)")
    sp.add_argument("--workdir", required=True, type=path_arg,
                    help="checkpoints, config.json, data.json, metrics.jsonl (a new folder or "
                    "one of `train`'s; one run at a time: a second is refused)")
    sp.add_argument("--steps", type=nonnegative_int, default=1000,
                    help="total steps (resumes if fewer done)")
    sp.add_argument("--save-every", type=positive_int, default=100)
    sp.add_argument("--log-every", type=positive_int, default=10)
    sp.add_argument("--keep", type=positive_int, default=3, help="checkpoints kept")
    sp.add_argument("--minutes", type=positive_float,
                    help="wall-time budget; stops and saves after it")
    sp.add_argument(
        "--init-from",
        metavar="WORKDIR|MODEL",
        type=path_arg,
        help="a fresh run starts from the trained parameters of this workdir or pretrained "
        "model (name or directory; fresh optimizer): fine-tuning; a model without map layers "
        "can be extended with them",
    )
    add_distributed_args(sp, "training")
    sp.add_argument("--set", nargs="*", metavar="FIELD=VALUE", help="config overrides")
    sp.set_defaults(func=cmd_train)

    sp = sub.add_parser("reproduce", help="train a shipped model's recipe from scratch, "
                        "resuming where it stopped")
    sp.add_argument("recipe", help="recipe name (`scenegen_jax/recipes.py`), e.g. cpu-av2-womd")
    sp.add_argument("--workdir", required=True, type=path_arg,
                    help="one workdir per run and phase: WORKDIR/RUN/PHASE")
    sp.add_argument("--cache-dir", default="runs", help="where the recipe's caches are "
                    "prepared when missing (default: runs)")
    sp.add_argument("--data-root", default="../shared/data",
                    help="the folder holding the recipe's data sets (default: ../shared/data)")
    sp.add_argument("--run", nargs="+", metavar="RUN",
                    help="train only these runs of the recipe (default: all, in order)")
    sp.add_argument("--out", type=path_arg, help="export the recipe's model here when its run "
                    "is done (a new or empty folder, or an exported model to replace)")
    sp.set_defaults(func=cmd_reproduce)

    sp = sub.add_parser("export-model", help="write a workdir's parameters as a pretrained model")
    sp.add_argument("--workdir", required=True, type=path_arg)
    sp.add_argument("--step", type=int, help="checkpoint step (default: the latest)")
    sp.add_argument("--out", required=True, type=path_arg,
                    help="directory (config, parameters, manifest): a new or empty folder, or "
                    "an exported model to replace")
    sp.add_argument("--location-temperature", type=positive_float, metavar="T",
                    help="the location temperature `sample` and `evaluate` use with this model "
                    "unless told otherwise (recorded in the manifest; default: none, i.e. 1)")
    sp.set_defaults(func=cmd_export_model)

    sp = sub.add_parser("train-forecaster", help="train the motion forecaster whose features "
                        "give `evaluate`'s Features MMD, on caches with futures")
    _add_companion_args(sp, "reads: the SceneGen model's it measures",
                        "training caches (cache version 6: they hold the actors' futures)",
                        "its ADE/FDE against constant velocity", 1000, "forecaster/")
    sp.set_defaults(func=cmd_train_forecaster)

    sp = sub.add_parser("train-baseline", help="train a learned baseline of the paper's "
                        "Table 1 on the training caches")
    sp.add_argument("name", choices=["layoutvae"], help="the baseline")
    _add_companion_args(sp, "generates on: the SceneGen model's", "training caches (SceneGen's)",
                        "its Monte-Carlo NLL", 3000, "NAME/")
    sp.set_defaults(func=cmd_train_baseline)

    sp = sub.add_parser("models", help="list the pretrained models shipped with the package")
    sp.set_defaults(func=cmd_models)
