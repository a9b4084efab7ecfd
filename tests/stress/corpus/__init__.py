"""Table-driven corpus of bad inputs and faults, run against the real command-line entry points.

Each `Case` is an input built in a temporary folder, the command line of one metegs command, and the class of
outcome that command must give: ``clear`` (exit code 2, one ``error:`` line naming the file or field, no
traceback) or ``correct`` (exit code 0 and a result that `check` accepts). The rooms add their cases in the
``cases_*.py`` modules beside this one; ``python -m tests.stress.corpus`` prints the tally by class.
"""
