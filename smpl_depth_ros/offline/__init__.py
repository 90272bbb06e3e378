"""process_bag: run the reconstructor over a recorded ROS 2 bag, every frame accounted for.

    process_bag BAG [BAG ...] --out DIR [--params-file config/reconstructor.yaml]
                [--device cpu] [--depth-topic T] [--info-topic T] [--no-tracking]
                [-p name=value ...] [--storage mcap|sqlite3] [--compress]
                [--export-meshes ply|obj|glb] [--workers N] [--chunk-size N]
                [--ray [ADDRESS]] [--overwrite]

BAG is a rosbag2 directory (metadata.yaml + storage files) or a single .mcap / .db3 file,
read with `rosbags` (no ROS install needed) one message at a time. The depth
(`sensor_msgs/msg/Image`) and camera_info topics are found automatically when there is one
candidate. Frames go through the same `pipeline.Reconstructor` and the same parameters as
the live `reconstructor` node (its `--params-file` YAML, `/**: ros__parameters:`), with
tracking across consecutive frames. DIR receives:

* ``bag/``: the input topics copied unchanged plus the node's outputs (``<ns>/mesh``
  Marker, ``<ns>/segmentation`` rgb8 + ``<ns>/segmentation/labels`` mono8 Image,
  ``<ns>/smpl_params`` JointState, ``<ns>/skeleton`` MarkerArray, ``/diagnostics``), each
  output with its input frame's header and bag timestamp, in input order (MCAP unless
  ``--storage sqlite3``);
* ``results.npz``: one row per depth frame read (stamps, status, parameters, residual,
  timings; see `save_results`);
* ``meshes/<stamp_ns>.<fmt>`` with ``--export-meshes``;
* ``summary.json``: frames_read, processed, skipped by reason, mean timings, fps, peak RSS,
  and per worker (``per_worker``: frames, busy seconds, frames/s, failures). The same JSON
  is printed on stdout at the end.

Several bags, or a folder of bags: DIR holds one such output folder per bag, named after
it; the workers are loaded once for all; one JSON line per bag, the worst exit code.

Invariant: ``frames_read == processed + sum(skipped.values())``: a frame is either
processed or skipped with a reason ('no_camera_info', 'no_person', 'encoding',
'size_mismatch', 'deserialize', ... the `types.InputError` reasons).

Real bags: header stamps may go backwards (tracking is reset) or repeat (processed, marked
``duplicate``); depth frames that arrive before the first camera_info of their frame_id
wait for it (up to `MAX_WAITING_FOR_INFO` frames, then the oldest is skipped as
'no_camera_info', as is any still waiting at the end of the bag); unknown topics are
copied through; a truncated or corrupt bag stops the run with an error naming the file
and the position, keeping everything read before it (the readable part of a truncated
MCAP or sqlite3 file is recovered) and closing the output bag properly. Exit codes: 0
done, 1 unusable input or options, 3 the bag is damaged (partial results written), 130
interrupted (partial results written).

`--workers N` runs N processes, each with its own Reconstructor, on contiguous chunks of
frames (tracking restarts at each chunk); the output keeps the input order. `--ray` runs
them as Ray actors instead, on a local Ray or on a cluster (`--ray HOST:6379`), with the
same output.

Modules: `params` (the node's parameters), `bagread` (reading bags, damaged ones too),
`workers` (per-frame work and its runners), `ray_runner` (the runner on Ray), `run`
(`process_bag`, the pass over the bag, results), `cli` (the command line), `errors`.
"""
from smpl_depth_ros.offline.bagread import BagInput, Topic, select_topics
from smpl_depth_ros.offline.cli import (EXIT_DAMAGED, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE,
                                        build_parser, main)
from smpl_depth_ros.offline.errors import BagReadError, InterruptedBeforeStart, ProcessBagError
from smpl_depth_ros.offline.params import NODE_OPTIONS, config_from_params
from smpl_depth_ros.offline.run import DEFAULT_NS, MESH_FORMATS, process_bag, save_results
from smpl_depth_ros.offline.workers import OUTPUTS

__all__ = [
    'BagInput', 'Topic', 'select_topics',
    'EXIT_OK', 'EXIT_USAGE', 'EXIT_DAMAGED', 'EXIT_INTERRUPTED', 'build_parser', 'main',
    'BagReadError', 'InterruptedBeforeStart', 'ProcessBagError',
    'NODE_OPTIONS', 'config_from_params',
    'DEFAULT_NS', 'MESH_FORMATS', 'process_bag', 'save_results',
    'OUTPUTS',
]
