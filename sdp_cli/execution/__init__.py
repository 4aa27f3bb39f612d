"""Where work runs: executors of independent jobs (:mod:`.executor`, :mod:`.executor_base`, :mod:`.executor_dask`),
worker processes (:mod:`.workers`), interrupts (:mod:`.interrupts`) and the CPU kernels' level (:mod:`.kernels`).
Depends on nothing of sdp but its errors."""
