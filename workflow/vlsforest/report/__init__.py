"""Figures and report material of the comparison (see :mod:`vlsforest.report.figures`)."""
