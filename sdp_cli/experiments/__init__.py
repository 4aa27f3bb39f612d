"""Experiments: experiment files (:mod:`.experiment`), the runs a pipeline stands for (:mod:`.pipeline`), running
them (:mod:`.runner`) and estimating their cost (:mod:`.estimate`). Above the algorithm, below the CLI and the
reports."""
