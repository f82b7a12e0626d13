"""Univariate root finding and Bernstein forms."""
