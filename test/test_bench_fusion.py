"""bench/fusion.py's bookkeeping (no timing asserted): one pass of the fusion's processor over a
bag's recorded inputs takes every input the node takes and gives what sensing_pipeline gives."""

from pathlib import Path

from sensing_nodes.bags.input_bag import load_bag
from sensing_nodes.bags.storage import topic_counts
from sensing_nodes.bench.fusion import fusion_pass
from sensing_nodes.graph import pipeline

BAG = Path(__file__).resolve().parents[1] / 'bags' / 'nominal'


def test_one_pass_takes_the_node_inputs_and_gives_the_pipeline_outputs(tmp_path):
    cpu_s, inputs, outputs = fusion_pass(load_bag(BAG).messages)
    counts = topic_counts(BAG)
    # The shipped bag holds no keyframe matches: /wheel/odom and /imu/data are the inputs.
    assert inputs == counts['/wheel/odom'][1] + counts['/imu/data'][1] == 1101 + 4401
    produced = pipeline.run(BAG, tmp_path / 'out', ('complementary_fusion',), progress=False)
    assert outputs == produced['/odometry/filtered'] + produced['/tf'] > 1101
    assert cpu_s > 0.0
