"""Private: the machinery behind `kernels.rays`' sums of scaled copies (dispatch, custom derivatives, CPU and GPU loops)."""
