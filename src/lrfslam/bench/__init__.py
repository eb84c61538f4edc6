"""What the pipeline costs: every benchmark, in one place.

``lrfslam bench`` (:mod:`~lrfslam.bench.command`) prints one table from one run: the in-process
rows (:mod:`~lrfslam.bench.cost`) and the live processes' (:mod:`~lrfslam.bench.live`). The
others measure one thing each and run as ``python -m lrfslam.bench.<name>`` (each module's
docstring gives its command): ``stages`` (CPU per scan of each stage, one process), ``play``
(a log through the live processes), ``delivery`` (rates, drops and gaps under load), ``soak``
(hours, memory sampled), ``mapper_growth``, ``map_message``, ``scan_match``, ``features``,
``instructions_features`` (callgrind), ``sim``, ``lms200``. Figures are ratios and rates within
one run on one machine; no test asserts a time.
"""
