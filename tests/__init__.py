"""edgerecon's tests, one folder per package (run: pytest)."""
