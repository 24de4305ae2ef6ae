"""The paper's figures, drawn with matplotlib from result files only (never from logs or MLflow).

Every figure is written as PNG and PDF with the data it draws as CSV beside it (:func:`common.save_figure`);
each states its profile and data source in a corner and names the paper's figure it reproduces in its caption.

The package sets matplotlib's Agg backend (files only, no display) as it is imported, so before any of its modules
imports ``matplotlib.pyplot``.
"""
import matplotlib

matplotlib.use("Agg")
