"""The commands run on a trained run: ``s2camp-export-cameras`` and ``s2camp-eval`` (test-time alignment)."""
