"""Benchmark scripts behind ``d2a bench``: they print figures, they assert nothing."""
