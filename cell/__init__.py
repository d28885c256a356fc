"""testcell: an emulated engine test cell that speaks CAN.

``cell`` holds everything that runs without HTTP: the DBC codec, the bus, the plant
simulator, the cyclic runtime and its blocks (filters, scripts, observers, controllers).
"""

__version__ = "0.1.0"
