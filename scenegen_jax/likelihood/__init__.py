"""The likelihood of a scene under the model: the teacher-forced unroll (`unroll`), its batches
(`batch`), its window-by-window gradients for training (`grads`) and the scene NLL from its
per-step terms (`terms`). Training (`train/`) and
evaluation (`eval/`) both build on it; it imports neither."""
