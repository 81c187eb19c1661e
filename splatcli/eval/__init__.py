"""Evaluation: metrics, scoring held-out views, Gaussian budgets, the training curve and reports."""
