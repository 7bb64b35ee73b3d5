"""The machinery behind `kernels.rays`' sums of scaled copies (dispatch, custom derivatives, CPU and GPU loops).

Public so that the loops can be tested one by one against each other and against NumPy; the rest of the library
reaches them only through `kernels.rays` (tests/test_architecture.py).
"""
