"""The application around the library ``ssm_ms``: the experiments of this repository and what it makes of their
results. The experiment registry (``configs/experiments.yaml``) and ``make reproduce`` (:mod:`experiments.reproduce`),
the markdown reports of the results files beside the paper's tables (:mod:`experiments.results`) and of the
identification benchmarks' beside their published baselines (:mod:`experiments.benchmark_results`), the README's
tables (:mod:`experiments.readme`), scores over seeds (:mod:`experiments.seeds`) and the command line that renders
the reports of the runs it tests (:mod:`experiments.cli`, ``python cli.py``).

``ssm_ms`` and ``datamodules`` never import this package (tests/test_imports.py)."""
