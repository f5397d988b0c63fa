"""The SceneGen network (Flax Linen): ConvLSTM, backbone and heads. No losses here."""
