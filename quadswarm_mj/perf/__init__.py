"""Speed code that measurements show pays, opt-in, each with a same-values test.

Each module here holds one trick aimed at a measured cost (most of them XLA:CPU's), a plain default
beside it where one serves, and a test showing the trick returns the same values as the default
(``tests/test_perf_*.py``). The model and the engines call these through their public names only.
"""
