"""Torch side: the differentiable game layer, networks, losses, metrics, training."""
