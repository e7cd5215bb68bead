"""`python -m e3cm_bench.cli`, the same as `python -m e3cm_bench` and the `e3cm-bench` command."""

from e3cm_bench.__main__ import main

if __name__ == "__main__":
    main()
