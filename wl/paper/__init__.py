"""Section IV of Nezhadali & Eriksson reproduced with this project's model: Figs. 6-9 and a comparison table.

:func:`wl.paper.run.reproduce` (``scripts/reproduce_paper.py``) takes the optima from
:mod:`mpc.benchmark.optima`, analyses them (:mod:`wl.paper.analysis`), draws the figures
(:mod:`wl.paper.figures`) and writes the table (:mod:`wl.paper.table`).
"""
