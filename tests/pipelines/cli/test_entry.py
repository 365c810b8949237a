"""What every command shares: one-line errors with exit codes, and `sandro-bench` loading only what it runs."""

import subprocess
import sys

import pytest

from pipelines.cli.entry import EXIT_ABORTED, EXIT_REFUSED, CommandError, Parser, run_command


def _parser() -> Parser:
    parser = Parser(prog="tool")
    parser.add_argument("--n", type=int, default=1)
    return parser


@pytest.mark.parametrize(
    ("error", "code", "line"),
    [
        (CommandError("bad --n"), 2, "tool: error: bad --n"),
        (CommandError("refused, nothing written: no overlap", EXIT_REFUSED), 1, "tool: refused, nothing written: no"),
        (ValueError("x.yaml: not valid\nYAML"), 2, "tool: error: x.yaml: not valid YAML"),
        (OSError("cannot write"), 2, "tool: error: cannot write"),
        (KeyboardInterrupt(), EXIT_ABORTED, "tool: aborted"),
    ],
)
def test_errors_become_one_line_and_an_exit_code(capsys, error, code, line):
    def command(args):
        raise error

    assert run_command(_parser(), command, []) == code
    err = capsys.readouterr().err
    assert err.startswith(line) and err.count("\n") == 1


def test_argument_errors_and_help_return_their_code(capsys):
    assert run_command(_parser(), lambda args: 0, ["--n", "x"]) == 2
    assert capsys.readouterr().err.startswith("tool: error: argument --n")
    assert run_command(_parser(), lambda args: 0, ["--help"]) == 0
    assert run_command(_parser(), lambda args: args.n, ["--n", "7"]) == 7


def test_sandro_bench_help_imports_no_benchmark():
    script = (
        "import sys, contextlib, io\n"
        "from pipelines.cli.bench import main\n"
        "with contextlib.redirect_stdout(io.StringIO()) as out:\n"
        "    code = main(['--help'])\n"
        "heavy = sorted(m for m in ('numpy', 'gtsam', 'open3d', 'pipelines.bench.slam') if m in sys.modules)\n"
        "print(code, heavy, 'registration' in out.getvalue())\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert result.stdout.split() == ["0", "[]", "True"]
