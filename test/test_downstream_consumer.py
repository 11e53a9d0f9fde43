"""A downstream consumer (slam_toolbox, nav2) of the running graph: test/tf_consumer.py, a separate
rclpy process that imports nothing from sensing_nodes, listens while sensing_demo runs the whole
graph on the simulated robot, and gives its verdict as JSON: the tree odom -> base_link -> laser,
every scan transformable (an odom -> base_link sample at or after its stamp within 0.1 s), no
transform stamped ahead of the inputs, no stamp repeated."""

import json
import os
import subprocess
import sys
from pathlib import Path

from harness import run_to_exit

CONSUMER = Path(__file__).with_name('tf_consumer.py')
DURATION_S = 10.0     # simulated: 100 scans
# The simulator waits for the fused answer to each scan before the next: a loaded machine slows
# the run down instead of making the fusion drop late inputs (what a consumer would then see is
# the machine's overload, not the graph's TF).
PACED = 'sensor_sim:pace_topic:=/odometry/filtered'
# ... and starts once the consumer's /scan subscription is matched too (line_extractor,
# icp_matcher, the demo's recorder and the consumer): a consumer discovered late saw 1 scan.
WAIT_FOR_THE_CONSUMER = 'sensor_sim:wait_for_scan_subscribers:=4'


def _consume_while_the_demo_runs(tmp_path, *params):
    """The consumer's verdict on a sensing_demo run with these --param overrides."""
    env = {k: v for k, v in os.environ.items() if k != 'PYTHONPATH'}   # nothing of this package
    consumer = subprocess.Popen([sys.executable, str(CONSUMER)], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path)
    try:
        assert consumer.stderr.readline().strip() == 'ready', consumer.stderr.read()
        demo = run_to_exit('sensing_demo', [
            '--duration', str(DURATION_S), '--domain-id', os.environ['ROS_DOMAIN_ID'],
            '--out', str(tmp_path / 'demo'), '--quiet',
            *[a for p in (PACED, WAIT_FOR_THE_CONSUMER, *params) for a in ('--param', p)]],
            timeout=300)
        assert demo.returncode == 0, demo.stdout + demo.stderr
        out, err = consumer.communicate(timeout=60)
    finally:
        if consumer.poll() is None:
            consumer.kill()
            consumer.wait()
    assert consumer.returncode == 0, err
    verdict = json.loads(out.strip().splitlines()[-1])
    print(json.dumps(verdict, indent=1))   # shown when a test fails
    return verdict


def test_a_foreign_consumer_can_transform_every_scan(tmp_path):
    verdict = _consume_while_the_demo_runs(tmp_path)
    # /scan is best effort: a consumer process starved of CPU loses some (82 of 100 in one
    # clean-clone run on a loaded 2-core machine); what it receives must all transform.
    assert verdict['scans'] >= 0.7 * DURATION_S * 10, verdict
    assert verdict['chains'] == {'laser': ['odom', 'base_link', 'laser']}, verdict
    assert verdict['tree_ok'] and verdict['multiple_parents'] == [], verdict
    assert verdict['scans_without_sample_after'] == 0, verdict
    # Only scans before the fusion's first output lack an earlier sample (tf2 drops those, as it
    # does before any odometry runs). The fusion starts where every input has spoken: an input
    # whose first messages DDS delivered late delays it (one scan in one clean-clone run), a
    # fusion that starts late or never does fails here.
    assert verdict['scans_without_sample_before'] <= 5, verdict
    # The estimate's transform is never ahead of the inputs. (The simulator's own ground truth,
    # map -> base_link_truth, is the time source itself and is not held to it.)
    assert verdict['future_stamps'].get('odom->base_link', 0) == 0, verdict
    assert verdict['repeated_stamps'] == {}, verdict
    assert verdict['odom_base_samples'] <= verdict['odometry'], verdict


def test_the_consumer_sees_the_tree_broken_without_the_fusion_transform(tmp_path):
    verdict = _consume_while_the_demo_runs(tmp_path, 'complementary_fusion:publish_tf:=false')
    assert verdict['scans'] > 0 and verdict['odometry'] > 0, verdict
    assert not verdict['tree_ok'] and verdict['chains'] == {'laser': ['base_link', 'laser']}, \
        verdict
    assert verdict['scans_without_sample_after'] == verdict['scans'], verdict
