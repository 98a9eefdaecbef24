"""Online self-supervised adaptation of the single-view network (no ROS import).

While the graph maps, the network learns the scene it is in from what the graph already
produces: the selected multi-view depths of each keyframe (sparse metric targets) and the
photometric consistency between the keyframe and its posed neighbours (dense, metric
because the poses are). It never sees ground truth.

* ``config.py``   AdaptConfig: learning rates, steps per keyframe, buffer, loss weights, guard
* ``sample.py``   AdaptSample: one keyframe's training signals; built from depth + score maps
* ``warp.py``     inverse warping of a posed neighbour into the keyframe with a depth map
* ``losses.py``   sparse log-depth L1, SSIM+L1 photometric (min over neighbours, auto-mask),
                  edge-aware smoothness
* ``prepared.py`` a sample's tensors on the device, depth-independent parts made once
* ``batch.py``    one step's loss for the whole batch at once (keyframes x neighbours)
* ``replay.py``   ReplayBuffer of past keyframes (against forgetting)
* ``snapshot.py`` weights + optimiser state before an update, in preallocated buffers
* ``inference_copies.py`` eval copies for inference, refilled in place once released
* ``guard.py``    held-out multi-view points: score an update, decide on a rollback
* ``adapter.py``  Adapter: train on one keyframe (+ replay), guard, roll back, version weights
* ``online.py``   OnlineAdaptation: the Adapter on its own thread, weights swapped atomically
* ``remote_adapter.py`` RemoteAdapter: the Adapter's interface over a training process
* ``trainer_process.py`` that process (niced before it imports torch; one update at a time)
"""
