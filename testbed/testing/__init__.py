"""Scenario test suites: expectations on a run's ``report.json``, the ``dopeslam test`` runner,
JUnit XML, ``summary.json``, ``report.html`` and regression baselines."""
