"""Reports: the self-contained HTML builder (:mod:`.html`) and one module per report."""
