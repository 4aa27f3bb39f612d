"""``sdp report``: two pipelines over the same evaluation rows.

- :mod:`sdp_cli.report.make` writes ``results/<experiment>/`` from run folders (:mod:`~sdp_cli.report.runs`),
  or extends a committed one (:mod:`~sdp_cli.report.carry`): every figure of :mod:`sdp_cli.report.figures`;
- :mod:`sdp_cli.report.ledger` writes ``results/PAPER.md`` from the committed reports and results/claims.yaml.

Both select rows in one place, :mod:`sdp_cli.report.rows`.
"""
