"""What every layer above ``kernels`` shares: the tape helpers (:mod:`core.tape`), device buffers
and recorded launches (:mod:`core.buffers`), Warp's initialisation (:mod:`core.device`), host
rotation helpers (:mod:`core.rotation`) and the one module that reaches into Warp's internals
(:mod:`core.warp_adapter`). It imports nothing from ``collision``, ``sim`` or ``scenes``."""
