"""The PyTorch reference (`../shared/bench/torch_ref`) on a CUDA device, for `bench/run.py
--suite accel`: the same model, random inputs, train step, scorer and sampling step as the
reference's own harness (its `bench.py` times on the CPU only), here with every tensor on the
GPU and each timed call ended by `torch.cuda.synchronize()`.

    python bench/torch_ref_cuda.py train --grid 320 --steps 25 --batch 1 [--bf16] [--ref DIR]

Prints one `RESULT {json}` row in the reference harness's format (its `summary` fields and
FLOP formula), plus `peak_device_GiB` (torch.cuda.max_memory_allocated). PyTorch's defaults
are kept: cuDNN convolutions may use TF32, as XLA's default precision does on this GPU.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import torch

DEFAULT_REF = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..",
                                            "..", "shared", "bench", "torch_ref"))


def timed(fn, runs: int, warmup: int) -> list[float]:
    for _ in range(warmup):
        fn()
    torch.cuda.synchronize()
    out = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        out.append(time.perf_counter() - t)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("kind", choices=("train", "score", "sample"))
    p.add_argument("--ref", default=DEFAULT_REF, help="the reference's folder (model.py, bench.py)")
    p.add_argument("--grid", type=int, default=128)
    p.add_argument("--steps", type=int, default=25)
    p.add_argument("--batch", type=int, default=1)
    p.add_argument("--map-ch", type=int, default=11)
    p.add_argument("--proposals", type=int, default=10)
    p.add_argument("--existing", type=int, default=16)
    p.add_argument("--neg-k", type=int, default=10000)
    p.add_argument("--bf16", action="store_true")
    p.add_argument("--channels-last", action="store_true")
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--warmup", type=int, default=2)
    a = p.parse_args()
    if not torch.cuda.is_available():
        sys.exit("torch_ref_cuda.py: no CUDA device")
    sys.path.insert(0, a.ref)
    import model as M

    import bench as R  # the reference's harness: its FLOP formula and summary

    torch.set_default_device("cuda")
    torch.manual_seed(0)
    g = torch.Generator(device="cuda").manual_seed(0)
    model = R.set_mode(M.SceneGen(map_ch=a.map_ch), a.channels_last, a.bf16)
    c_in = a.map_ch + M.ACTOR_CHANNELS
    row = {"batch": a.batch, "grid": a.grid, "map_ch": a.map_ch, "bf16": a.bf16,
           "channels_last": a.channels_last, "device": torch.cuda.get_device_name(),
           "torch": torch.__version__, "cudnn_tf32": torch.backends.cudnn.allow_tf32}
    if a.kind in ("train", "score"):
        x_seq, tgt = M.random_inputs(a.steps, a.batch, a.map_ch, a.grid, a.grid, gen=g)
        if a.channels_last:
            x_seq = R.seq_channels_last(x_seq)
        if a.kind == "train":
            opt = torch.optim.Adam(model.parameters(), lr=1e-4)
            model.train()

            def fn():
                return M.train_step(model, opt, x_seq, tgt, a.neg_k)
        else:
            model.eval()

            def fn():
                with torch.inference_mode():
                    return M.scene_nll(model, x_seq, tgt, a.neg_k)
        s = R.summary(timed(fn, a.runs, a.warmup))
        fwd, tr = R.run_flops(a.steps, a.grid, a.grid, c_in)
        flops = (tr if a.kind == "train" else fwd) * a.batch
        row.update(what="train_step" if a.kind == "train" else "score_fwd", steps=a.steps, **s)
        row["scenes_per_s"] = a.batch / s["median_s"]
    else:
        model.eval()
        scene = M.random_scene(model, a.batch, a.grid, a.grid, n_existing=a.existing, gen=g)
        if a.channels_last:
            scene.x = scene.x.contiguous(memory_format=torch.channels_last)
        alive = scene.alive.clone()

        def fn():
            scene.alive = alive.clone()  # every element keeps generating, as in bench.py
            M.sample_step(model, scene, a.proposals)
        s = R.summary(timed(fn, a.runs, a.warmup))
        flops = R.step_flops(a.grid, a.grid, c_in)["total"] * a.batch
        row.update(what="sample_step", proposals=a.proposals, **s,
                   per_scene_ms=1e3 * s["median_s"] / a.batch)
    row.update(GFLOP=flops / 1e9, GFLOPs_per_s=flops / 1e9 / s["median_s"],
               peak_device_GiB=round(torch.cuda.max_memory_allocated() / 2**30, 3))
    print("RESULT " + json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
