"""Reports for people: the HTML page of ``coreg diagnose --report`` (matplotlib, Agg)."""
