"""bench/messages.py's bookkeeping (no timing asserted): the processors take every input their
nodes take (the gyro integrator's /wheel/odom being the wheel processor's outputs), and give
what sensing_pipeline gives; every decoder is timed on every message of its type."""

from pathlib import Path

from sensing_nodes.bags.input_bag import load_bag
from sensing_nodes.bags.storage import BagReader, topic_counts
from sensing_nodes.bench.messages import _time_node, decoding, processors
from sensing_nodes.graph import pipeline

BAG = Path(__file__).resolve().parents[1] / 'bags' / 'nominal'


def test_processors_take_the_node_inputs_and_give_the_pipeline_outputs(tmp_path):
    bag = load_bag(BAG)
    counts = topic_counts(BAG)
    figures = processors(bag)
    assert figures['wheel_odometry_messages'] == counts['/joint_states'][1] == 1101
    assert figures['gyro_integrator_messages'] == counts['/imu/data_raw'][1] + 1101
    assert figures['line_extractor_messages'] == counts['/scan'][1] == 220
    assert all(figures[f'{n}_us_per_message'] > 0.0
               for n in ('wheel_odometry', 'gyro_integrator', 'line_extractor'))
    # The outputs the bench's passes produce are sensing_pipeline's, byte for byte.
    rows = [(t, s, raw) for t, s, raw in bag.messages]
    _, _, wheel = _time_node('wheel_odometry', rows)
    pipeline.run(BAG, tmp_path / 'out', ('wheel_odometry',), progress=False)
    expected = [(s, bytes(raw)) for t, s, raw in BagReader(tmp_path / 'out').raw()
                if t == '/wheel/odom']
    assert [(s, bytes(raw)) for _, s, raw in wheel] == expected


def test_every_decoder_is_timed():
    figures = decoding(load_bag(BAG))
    for name in ('imu', 'joint_state', 'laser_scan', 'odometry'):
        assert figures[f'decode_{name}_us'] > 0.0 and figures[f'decode_{name}_rosbags_us'] > 0.0
