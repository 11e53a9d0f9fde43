"""Command-line tools: plots, evaluations, bag utilities."""
