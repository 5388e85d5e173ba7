"""Reports for people: HTML pages and figures (matplotlib, Agg canvas only)."""
