"""Design tools: each turns a recorded log into an observer's calibration file (gain tables,
bias augmentations), registered in :data:`cell.core.registry.DESIGNS` and run as
``testcell design NAME LOG``; the runtime loads the file with the block set's own option.
"""
