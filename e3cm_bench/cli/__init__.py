"""e3cm-bench's command line: one thin function per subcommand, in modules by what they work on.

common.py holds the application, its consoles, the options several commands share and the
one-line error wrapper; each other module registers its commands on that application when it
is imported, in the order `e3cm-bench --help` lists them: match, the benchmark commands
(generated from the benchmark registry), the commands over run folders, the tools, and the
data commands.
"""

from e3cm_bench.cli import match  # noqa: F401, I001 - each module adds its commands to app, in this order
from e3cm_bench.cli import benchmarks  # noqa: F401
from e3cm_bench.cli import reconstruct  # noqa: F401
from e3cm_bench.cli import results  # noqa: F401
from e3cm_bench.cli import tools  # noqa: F401
from e3cm_bench.cli import data  # noqa: F401
from e3cm_bench.cli.common import app, os_error_line, parse_settings

__all__ = ["app", "os_error_line", "parse_settings"]
