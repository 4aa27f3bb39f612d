"""The TO families, named once: what every ``--to`` (and an experiment group's ``to:``) accepts, the default,
and how reports name each family's solver. A leaf module (it imports nothing), so configs and reports use it
without loading the optimizers (:mod:`sdp_cli.trajopt` builds the solvers)."""

#: the default family: our multiple shooting solved by fatrop (the main TO of every experiment)
DEFAULT_TO = "ms"
#: family -> the name reports give its solver; ``ddp`` is box-FDDP, the paper's solver family
TO_NAMES = {DEFAULT_TO: "fatrop", "ddp": "box-FDDP"}
TO_FAMILIES = tuple(TO_NAMES)
