"""``/controllers``: the PI back-pressure controllers (``{"enable": true}``, ``{"kp": ..}``, ...)."""

from .blocks import block_router

router = block_router("controller", "/controllers",
                      [{"enable": True}, {"setpoint": 680.0, "feedback": "EXH_BP_R_Kalman"},
                       {"kp": 0.005, "ki": 0.013}])
