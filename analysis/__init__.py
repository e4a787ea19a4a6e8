"""Analysis of stored cdqn runs: the paper's table and figures from an MLflow store.

    python analysis/make_table.py                     # Markdown on stdout, CSV + LaTeX files
    python analysis/make_figures.py --out figures/    # every figure, PNG and PDF

:mod:`analysis.runs` loads runs, episode metrics and per-step artifacts into pandas;
:mod:`analysis.table` and :mod:`analysis.figures` turn them into the paper's evidence;
:mod:`analysis.shared` declares what the agents of one column share and :mod:`analysis.columns`
finds where they differ; :mod:`analysis.claims` tests the paper's claims on the runs.
"""
