"""Where work runs: executors of independent jobs (:mod:`.executor`, :mod:`.executor_base`, :mod:`.executor_dask`),
worker processes (:mod:`.workers`) and interrupts (:mod:`.interrupts`).
Depends on nothing of sdp but its errors."""
