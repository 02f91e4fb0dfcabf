"""Reports: JSON results of the benchmark and stability suites turned into Markdown + PNG
and a self-contained HTML page (``python -m reports.report RESULTS... -o DIR``)."""
