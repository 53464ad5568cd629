"""Benchmarks of tunnelsim: ``python -m benchmarks`` (see :mod:`benchmarks.__main__`) runs them all
and writes ``benchmarks/results/*.md`` / ``*.png``; each module also runs alone as a script."""
