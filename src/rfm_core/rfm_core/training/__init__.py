"""Training and fitting of rfm's learned parts on simulated scenes (seeds 3000+): the learned
object matcher (:mod:`.matcher`, ``rfm train-matcher``), depth_clusters' calibrated score
(:mod:`.depth_score`, ``rfm train-depth-score``) and its box refiner (:mod:`.box_refiner`,
``rfm train-box-refiner``). The runtime packages (detection, matching,
mapping) never import this package, nor the simulator or the evaluation."""
