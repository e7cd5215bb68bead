"""Everything that reads finished runs and shows them: paper-layout tables and console summaries
(tables.py), plots (plots.py), the static report site (site.py), two runs compared pair by pair
(compare.py), the regression check with its noise model (check.py, noise_gate.py, ensemble.py),
and how numbers are printed (formats.py). Nothing here matches or recomputes a metric."""
