"""README's command blocks run as written, all but the "Commands" reference (`test_readme_command_reference.py`,
a file of its own so that the two longest blocks can run on two test workers at once). How: `readme_blocks.py`."""

import pytest

import readme_blocks as rb


def test_the_blocks_are_found():
    blocks = rb.command_blocks()
    assert len(blocks) >= 4 and all(lines for _, lines in blocks)
    assert any(line.startswith("ffcgs grasp mug") for _, lines in blocks for line in lines)
    assert any(line.startswith("ffcgs dataset build --keep all") for line in blocks[rb.REFERENCE][1])


def test_comments_are_dropped_but_not_quoted_hashes():
    assert rb.strip_comment('ffcgs show grasps.npz   # a view (pip install -e ".[viz]")') == "ffcgs show grasps.npz"
    assert rb.strip_comment("echo '#x' # y") == "echo '#x'"


@pytest.mark.e2e
@pytest.mark.parametrize("lines", [pytest.param(lines, id=f"line{start}")
                                   for k, (start, lines) in enumerate(rb.command_blocks()) if k != rb.REFERENCE])
def test_readme_block_runs_as_written(lines, tmp_path, tmp_path_factory):
    rb.run_block(lines, tmp_path, tmp_path_factory)
