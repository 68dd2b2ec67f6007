"""README's "Commands" block (the command reference) runs as written, line by line (`readme_blocks.py`)."""

import pytest

import readme_blocks as rb


@pytest.mark.e2e
def test_readme_command_reference_runs_as_written(tmp_path, tmp_path_factory):
    _, lines = rb.command_blocks()[rb.REFERENCE]
    rb.run_block(lines, tmp_path, tmp_path_factory)
