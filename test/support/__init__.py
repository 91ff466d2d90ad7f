"""Helpers shared by the tests, imported as ``support.<module>`` (``test/`` is on ``sys.path``: pytest's
``pythonpath`` in pyproject.toml; a launch test run by plain ``launch_test`` puts it there itself). No tests here.
"""
