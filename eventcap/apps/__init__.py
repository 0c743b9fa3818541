"""What a user runs: the command line, the benchmark and its open suite, reports, the run's output files and the
viewer. Apps use the framework (:mod:`eventcap.core`) and the domain library; nothing below imports them."""
