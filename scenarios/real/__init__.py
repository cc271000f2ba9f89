"""Readers of recorded motion into the dataset format (:mod:`scenarios.dataset`).

- :mod:`scenarios.real.scenes`: windows, states from positions, the interaction rule,
  padding and the crowd game, shared by every reader.
- :mod:`scenarios.real.recipe`: the recipe fields every reader shares.
"""
