"""Weight-space interpolation between a model and its fine-tune (WiSE-FT, Wortsman et al.
2022): writes, for each `--alpha` a, a pretrained model directory whose parameters are
(1 - a) * START + a * TUNED, leaf by leaf, for `scenegen score/sample/evaluate --pretrained DIR`.

    .venv/bin/python experiments/interpolate.py --start runs/base \
        --tuned runs/finetune --alpha 0.25 0.5 0.75 --out runs/wise

writes runs/wise/a0.25/ and so on; `--keep NAME ...` takes those top-level parameters
from START unchanged (e.g. its box MLP). START is a training workdir (its latest checkpoint)
or a pretrained model, as `--init-from` takes it; TUNED is the fine-tune's workdir (its
latest checkpoint, or the moving average of a run with `ema_decay`). They must be the same
model, so that their parameter trees match leaf for leaf (same structure and shapes). The
written config is START's.
"""

from __future__ import annotations

import argparse
import json
import os

import jax

from scenegen_jax.pretrained import save_pretrained
from scenegen_jax.train.warm_start import start_params
from scenegen_jax.workdir import load_params


def interpolate(start: dict, tuned: dict, alpha: float, keep: tuple[str, ...] = ()) -> dict:
    """(1 - alpha) * start + alpha * tuned, leaf by leaf (same tree structure and shapes),
    except the top-level parameters named in `keep`, which stay start's."""
    return {
        name: start[name] if name in keep
        else jax.tree.map(lambda a, b: (1.0 - alpha) * a + alpha * b, start[name], tuned[name])
        for name in start
    }


def same_tree(a: dict, b: dict) -> bool:
    """Whether two parameter trees have the same structure and leaf shapes."""
    if jax.tree.structure(a) != jax.tree.structure(b):
        return False
    pairs = zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    return all(x.shape == y.shape for x, y in pairs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--start", required=True, help="workdir or pretrained model")
    ap.add_argument("--tuned", required=True, help="the fine-tune's workdir")
    ap.add_argument("--alpha", type=float, nargs="+", required=True,
                    help="weights of TUNED, each in [0, 1]")
    ap.add_argument("--keep", nargs="+", default=[], metavar="NAME",
                    help="top-level parameters taken from START unchanged (e.g. the box MLP's "
                    "box0_b box0_map_w ...)")
    ap.add_argument("--location-temperature", type=float, default=0.7,
                    help="the sampler setting recorded in each manifest")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    for a in args.alpha:
        if not 0.0 <= a <= 1.0:
            raise SystemExit(f"--alpha {a}: must lie in [0, 1]")
    cfg_s, start = start_params(args.start)
    cfg_t, tuned, step_t = load_params(args.tuned)
    if cfg_s.model != cfg_t.model:
        raise SystemExit(f"{args.start} and {args.tuned}: not the same model ("
                         f"{'; '.join(d for d in cfg_s.differences(cfg_t))})")
    if not same_tree(start, tuned):
        raise SystemExit(f"{args.start} and {args.tuned}: not the same model (their parameter "
                         "trees differ in structure or shapes)")
    unknown = sorted(set(args.keep) - set(start))
    if unknown:
        raise SystemExit(f"--keep {' '.join(unknown)}: no such parameters; the model has "
                         f"{' '.join(sorted(start))}")
    for a in args.alpha:
        out = os.path.join(args.out, f"a{a:g}")
        source = f"{a:g} x {args.tuned} (step {step_t}) + {1 - a:g} x {args.start}"
        if args.keep:
            source += f", {' '.join(args.keep)} from {args.start}"
        params = interpolate(start, tuned, a, tuple(args.keep))
        manifest = save_pretrained(out, cfg_s, params, step_t, source,
                                   {"location_temperature": args.location_temperature})
        print(json.dumps({"out": out, **manifest}))


if __name__ == "__main__":
    main()
