"""torchheat — one-point isometric shape matching with the heat kernel, batched in PyTorch."""
