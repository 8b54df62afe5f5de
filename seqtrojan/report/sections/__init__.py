"""The report's sections, one module each: every one takes typed results and returns its HTML parts (a list of
strings that :func:`seqtrojan.report.html.build_report` joins with newlines)."""
