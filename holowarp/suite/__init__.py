"""Dataset runs (issue 18): every object of a suite file through synth, the visual-hull
baseline, reconstruct, evaluate and simulate, on Ray or in-process, and the paper's tables.

- :mod:`holowarp.suite.spec`: the suite file format (documented there) and its checks;
- :mod:`holowarp.suite.work`: one object's steps, each skipped when its output is there;
- :mod:`holowarp.suite.summary`: ``summary.json`` / ``summary.md`` from the objects' files;
- :mod:`holowarp.suite.run`: :func:`run_suite`, the output folder and the executors.

One call runs a suite::

    from holowarp.suite import run_suite
    summary = run_suite("suite.toml", "runs/suite", executor="ray")
"""

from holowarp.suite.run import run_suite
from holowarp.suite.spec import ObjectSpec, Suite, SuiteError, load_suite, recon_config
from holowarp.suite.summary import format_markdown, summarise, write_summary
from holowarp.suite.work import run_object

__all__ = ["run_suite", "load_suite", "recon_config", "run_object", "summarise", "write_summary", "format_markdown",
           "Suite", "ObjectSpec", "SuiteError"]
