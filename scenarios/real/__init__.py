"""Readers of recorded motion into the dataset format (:mod:`scenarios.dataset`).

- :mod:`scenarios.real.eth_ucy`: ETH/UCY pedestrian text files, scenes of a focal pedestrian.
- :mod:`scenarios.real.vci`: vehicle-crowd clips in the CITR layout, a vehicle and pedestrians.
- :mod:`scenarios.real.waymo`: Waymo Open Motion ``Scenario`` records, scenes of a pair.
- :mod:`scenarios.real.tfrecord`: TFRecord framing and CRC-32C checks, no TensorFlow.
- :mod:`scenarios.real.waymo_schema`: the Waymo ``Scenario`` protocol buffer schema used.
- :mod:`scenarios.real.scenes`: windows, states, interaction rule, padding, crowd game (shared).
- :mod:`scenarios.real.recipe`: the recipe fields every reader shares.
"""
