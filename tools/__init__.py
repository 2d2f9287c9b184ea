"""telesurg tools: the benchmarks, the paper experiments and the device emulators, beside the runtime.

They drive and compose the runtime (``telesurg.shared``, ``telesurg.services``); the runtime never
imports them. Their heavy dependencies (matplotlib, psutil, mink) come with the ``lab`` extra:
``pip install 'telesurg[lab]'``.
"""
