"""Tunables and their defaults, one comment each. Per-dataset values live in ``configs/*.toml``.
Every fixed number that can change a result row lives here (all of them enter the parameter hash); no logic."""

from __future__ import annotations

# --- model (docs/method.md) ---
DEFAULT_MODEL = "bev"  # BEV is what the paper evaluates and what most label tools show
DEFAULT_SIGMA = 0.2  # LiDAR noise std in metres; the paper uses 0.2 for KITTI, 0.3 for Waymo
DEFAULT_NUM_NEAREST = 3  # M: surface points each LiDAR point may be registered to (paper: 3)
DEFAULT_PRIOR_WEIGHT = 1.0  # w: the prior covariance is divided by w (larger = trust annotators more)
DEFAULT_MIN_POINTS = 3  # boxes with fewer points get status "few_points" (still inferred; prior dominates)
SIGMA_FLOOR = 0.01  # lower bound (m) on an EM noise estimate used as σ, so exact-fit points cannot give σ = 0
EM_MAX_ITERATIONS = 50  # cap on EM iterations for the noise σ̂ (per object and per dataset)
EM_TOLERANCE = 1e-3  # EM stops when σ̂ changes by less than this fraction (σ̂ is reported to ~mm)
EM_RESIDUAL_DOF = (
    1.0  # noise components left in a residual to the nearest surface point (the normal); D would give σ/√D
)
OUTLIER_REGION_MARGIN = 0.5  # m; the uniform outlier density is 1 / size of the box grown by this on every side
PRIOR_SHEAR_STD_RATIO = 1.0  # prior std of the axis-angle difference a−b (parallelogram shear) / the yaw std

# --- label-error model (docs/label-error.md) ---
FIT_MAX_ITERATIONS = 30  # cap on EM iterations of the box fit (suggested box)
FIT_STEP_HALVINGS = 16  # box fit: a step that raises the fit's cost is halved back up to this many times (a descent: real scans made plain EM steps overshoot and oscillate)
FIT_TOLERANCE = 1e-3  # m; the box fit stops when no entry of φ moves by more than this
FIT_STALL_STEP = 1e-3  # m; box fit with rays: a step shorter than this that still raises the cost ends the descent at the last box it accepted (the fit)
FIT_SMOOTHING = 0.02  # m; width of every switch of the box fit's ray rows: faces this near the nearest share a ray's row, the row switches on and the tolerance changes over this (the rows are continuous in the box)
FIT_SWAP_RESIDUAL = 0.5  # try an l/w-swapped start when the fit's RMS point-to-surface residual exceeds this × σ
FIT_INSIDE_SIGMA_RATIO = 3.0  # box fit: points deep inside the box count with σ × this, for the orientation of their face only (they never pull it in)
FIT_INSIDE_FREE_DEPTH = 0.05  # m; points less deep than this inside the box count fully (LiDAR noise, ~2σ)
FIT_OUTLIER_PROB = (
    0.0  # box fit: prior probability that a point outside the box is an outlier (uniform mixture; 0 = off)
)
FACE_GAP = 0.02  # m; how deep inside a right label's seen side face its lower body's outer surface lies (mean; label_error's face term; chosen by leave-one-frame-out on real KITTI among the values that keep the simulated benchmark ≥ 0.95)
FACE_GAP_STD = 0.08  # m; its spread over right labels (real KITTI seen faces: −0.08–0.17 m, standard deviation 0.056; chosen with FACE_GAP by leave-one-frame-out; docs/label-error.md)
FACE_GAP_QUANTILE = (
    0.1  # a seen face's outer surface: this quantile of its points' depths (robust to the few points outside it)
)
FACE_GAP_MIN_POINTS = 5  # a seen face with fewer registered points than this gives no face term
FIT_MIN_SIZE_FRACTION = 1e-3  # fitted sizes are kept ≥ this fraction of the label's (no collapse)
FREE_SPACE_CLASSES = (
    "Car",
    "Van",
    "Truck",
    "Vehicle",
    "REGULAR_VEHICLE",
    "LARGE_VEHICLE",
    "BUS",
    "SCHOOL_BUS",
    "ARTICULATED_BUS",
    "BOX_TRUCK",
    "TRUCK",
    "TRUCK_CAB",
)  # classes with a solid lower body (KITTI, Waymo, Argoverse 2 names): their fit uses free-space rays (legs, bikes, trailers and Misc are open)
LABEL_ERROR_CLASSES = FREE_SPACE_CLASSES  # label_error is written for vehicles only (validated on real KITTI and simulated vehicles); null for other classes (real KITTI pedestrians: AUROC 0.64, docs/label-error.md)
FREE_SPACE_SLAB = (
    0.25,
    0.4,
)  # solid lower body of a vehicle: from this height (m) above the local ground to this fraction of the box height
FREE_SPACE_TOLERANCE = 0.1  # m; τ: a ray counts as free space only where it passes deeper than this inside the box rectangle (rounded corners of real vehicles)
FREE_SPACE_INSIDE_TOLERANCE = 0.3  # m; τ of rays that end inside the box (on the object): real surfaces lie up to this far inside a right label (bumpers, loose boxes)
FREE_SPACE_REACH = (
    1.0  # m; rays are collected for the box grown by this, the furthest the fit may move and still see them
)
FREE_SPACE_WEIGHT = 1.0  # √weight of a free-space ray row relative to a point row in the box fit
FREE_SPACE_SLIT_PROB = 0.1  # prior probability that a ray through a right box's slab is a slit (cab–cargo gap, glass): the fit's ray rows are a robust mixture
FREE_SPACE_SIGHT_ANGLE = 0.004  # rad (0.23°: a little more than one column of KITTI's, Waymo's, AV2's scanners); a ray through a box's slab that passes beyond the box's returns on both sides of its azimuth within this is see-through, not free space
FREE_SPACE_SAME_RAY_ANGLE = 0.0005  # rad (0.03°); two returns this close in direction from the sensor lie on one ray (a second return): a single-return spinning lidar's beams are ≥ 0.14° apart
FREE_SPACE_AZIMUTH_BINS = 2048  # azimuth buckets of the frame's points for the ray selection (speed only)
LABEL_TOLERANCE = {
    "center": 0.10,
    "length": 0.20,
    "width": 0.20,
    "height": 0.10,
    "yaw": 0.02,
}  # offsets of about this std (m, rad) are not errors; sizes wider: the fit barely sees them (docs/label-error.md)

# --- tracks: every label judged against its own track (labelaudit/core/track.py, docs/method.md "Tracks") ---
TRACK_FORMATS = (
    "waymo-v1",
    "waymo-v2",
    "av2",
)  # dataset formats whose object ids are track ids (KITTI object: none, the columns stay null)
TRACK_WINDOW = 1.05  # s; a frame's centre and heading are predicted from the frames nearest in time within this (10 Hz: ±0.5 s inside a track, 1 s on one side at its ends)
TRACK_MAX_NEIGHBOURS = 5  # 2 × this many nearest frames (5 on each side inside a track)
TRACK_MIN_FRAMES = 3  # a track with fewer labelled frames cannot tell which label is wrong: null scores
TRACK_RATE_PRIOR = (
    40.0,
    6.0,
    1.5,
    0.5,
)  # std of the local fit's ridge prior: centre velocity m/s, acceleration m/s², yaw rate rad/s, yaw acceleration rad/s²
TRACK_NOISE_FLOOR = {
    "center": 0.03,
    "length": 0.03,
    "width": 0.02,
    "height": 0.03,
    "yaw": 0.015,
}  # m, rad; ordinary per-frame label noise is never taken below this (the run's own, pooled per class, when larger)
TRACK_NOISE_MIN_SAMPLES = 30  # residuals of a class needed before its own noise scale replaces the floor
TRACK_NOISE_BIN = 0.001  # the run's noise scale is the median of a histogram of |standardised residual| with bins this wide (memory independent of the run's size)
TRACK_NOISE_RANGE = (
    20.0  # … up to this; larger residuals share the last bin (a median beyond it would mean noise 20 × the floor)
)
TRACK_HUBER_K = 2.0  # Huber threshold of the first robust iterations (standardised residual)
TRACK_IRLS_ITERATIONS = (
    5  # reweighting rounds of every robust fit of a track (the first TRACK_HUBER_ITERATIONS Huber, the rest biweight)
)
TRACK_HUBER_ITERATIONS = 2  # the convex Huber weights first: a safe start before the biweight can give a label weight 0
TRACK_OUTLIER_ROUNDS = (
    4  # refits of a track's local fits, each leaving out one more frame that stands out among its neighbours
)
TRACK_NO_NEIGHBOUR_PRECISION = 1e-9  # prior precision of a local fit's intercept: a frame without neighbours gets a finite, enormous prediction variance (residual ~0), not a singular fit
TRACK_BIWEIGHT_C = 4.685  # Tukey biweight cut-off of the later iterations (95 % efficiency): gross outliers weigh 0
TRACK_ERROR_PRIOR = 0.02  # π: prior probability that a label contradicts its track
TRACK_ERROR_SCALE = (
    10.0  # k: a wrong label's residual is ~k times the ordinary noise (the broad component of the mixture)
)
TRACK_ISSUE_MIN = 0.5  # track_issue names a kind when its probability reaches this, else "none"
TRACK_FLAG = (
    0.9  # a frame with track_error at or above this counts as flagged in tracks.parquet (and the gate's default)
)
TRACK_MOVING_SPEED = (
    1.0  # m/s; a track faster than this in a frame is moving there (heading vs motion in tracks.parquet)
)

# --- spatial distribution p_G and JIoU (docs/method.md §6–7) ---
DEFAULT_CELLS_PER_SIDE = 64  # grid cells across the longer box side; JIoU stable ±0.01 when doubled
DEFAULT_NUM_SAMPLES = 128  # quasi-random (Sobol) samples of φ for form (b) of p_G (128 vs 1024: JIoU-GT within 0.003)
DEFAULT_SUPPORT_STD = 3.0  # grid extends this many corner stds beyond the box
DEFAULT_QMC_SEED = 0  # fixed so results are reproducible run to run
SUBROWS_PER_CELL = 1  # y sub-rows per grid row in the rasteriser (1 measured most accurate: row aliasing offsets the Jaccard cell bias)
MAX_CELLS_PER_AXIS = 256  # cap on grid cells per axis (tiny boxes with wide priors); cells grow instead
CELLS_PER_SIDE_3D_FACTOR = 1.0  # 3D voxel grids use this fraction of cells_per_side (cost grows with the cube)
CELL_STD_SPAN = 32.0  # cells_per_side spans max(box side, this × smallest edge std): cells ≈ std/2 for blurred boxes

# --- crop (docs/datasets.md) ---
DEFAULT_CROP_MARGIN = 0.1  # BEV margin in metres added around each box when selecting points
DEFAULT_FIT_CROP_MARGIN = 0.5  # wider BEV margin (m) of the points given to the label-error fit: a shifted box must still see its object (docs/label-error.md)
DEFAULT_GROUND_CUT = 0.1  # points within this height above the box bottom are ground, dropped
CROP_GRID_MIN_BOXES = (
    64  # frames with this many boxes are cropped through a BEV grid (same indices; Open3D per box costs K·N)
)
CROP_GRID_CELL = 2.0  # m; BEV grid cell of that crop (a car touches ~10 cells: few extra candidates, few runs)
CROP_GRID_BATCH = 256  # boxes per vectorised batch of that crop (bounds its temporary arrays)
CROP_GRID_DENSE_CELLS = (
    8  # the grid is built by a counting sort when it has at most this many cells per point (8 B each), else by a sort
)
GROUND_MARGIN = 1.5  # m; the local ground plane is fitted to points within the box grown by this in BEV
GROUND_WINDOW = (
    0.6  # m; … and within this height of the label's bottom (a wrong bottom by up to this still finds the ground)
)
GROUND_INLIER = 0.08  # m; a point within this of the plane is ground (LiDAR noise and road roughness)
GROUND_MIN_POINTS = 15  # fewer ground inliers than this: the fixed cut above the box bottom is used
GROUND_MAX_SLOPE = 0.10  # steeper planes (rise over run) are not ground (roads stay below ~8 %; car sides, kerbs)
GROUND_HYPOTHESES = 24  # RANSAC plane hypotheses per box, drawn from a fixed seed (reproducible rows)
GROUND_SCORED = 512  # RANSAC hypotheses are scored on at most this many ground candidates (an even stride)
SCENERY_VOXEL = 0.2  # m; BEV cell of the connectivity test for unlabelled surfaces (walls, hedges): a gap wider than two cells separates
NEIGHBOUR_MARGIN = (
    0.1  # m; points within this of another label (BEV) and outside the box itself are that label's, not evidence
)

# --- missing labels: the search for unlabelled objects (labelaudit/infer/missing.py, docs/missing.md) ---
MISSING_MAX_RANGE = 70.0  # m; default labelled range (KITTI labels to ~70 m; configs override per dataset)
MISSING_MIN_POINTS = 10  # a cluster with fewer non-ground points is not a candidate
MISSING_DETECTION_MIN_SCORE = 0.5  # detections below this confidence are not candidates (--detections)
MISSING_GROUND_CELL = 1.0  # m; cells of the ground estimate (a cell's ground comes from the 3 × 3 around it: a 3 m window, 15 cm off on a 10 % slope)
MISSING_CELL = 0.2  # m; BEV occupancy cells of the clustering (8-connected: a gap of two cells separates)
MISSING_LABEL_MARGIN = 0.3  # m; returns within this of a label (BEV, any class) are explained by it
MISSING_BAND = (0.3, 4.4)  # m above the ground: returns clustered (below: road, kerbs; above: signs, canopies)
MISSING_TALL = (
    6.0  # m; returns above the band up to this height mark structures that go on upwards (walls, poles, trunks)
)
MISSING_MAX_OVER_SHARE = (
    0.2  # a cluster with more returns above the band than this share of its band returns is a tall structure
)
MISSING_EGO_RADIUS = (
    3.0  # m; nothing whose centre is this close to the sensor (BEV) is a candidate: the ego vehicle and its mounts
)
MISSING_SIZE_SLACK = (
    0.5  # m; the size score falls from 1 to 0 over this much beyond a class's largest length, width or height
)
MISSING_MIN_TOP = (
    0.8,
    1.1,
)  # m; the size score rises from 0 to 1 as the highest return above the ground goes from the first to the second
MISSING_MIN_EXTENT = (
    0.8,
    1.2,
)  # m; … and as the longer visible side goes from the first to the second (poles, people, signs)
MISSING_UNSEEN_TOP_FACTOR = (
    0.3  # size score × this when the returns reach as high as the beams go at that range (top not seen: a wall?)
)
MISSING_TOP_CLEARANCE = (
    0.15  # m; the top is seen when the highest return is this far below the highest beam at the cluster's range
)
MISSING_FACE_BAND = (
    0.3,
    0.7,
)  # m above the ground: the lower body, whose returns lie on the vertical faces of a vehicle
MISSING_FACE_MIN_LOWER = 8  # a cluster with fewer lower-body returns than this is judged on all its returns for its faces (too few low returns to tell)
MISSING_FACE_WIDTH = 0.2  # m; slices across the box axes whose returns make a vertical face (LiDAR noise, bumpers)
MISSING_FACE_SHARE = (
    0.6,
    0.85,
)  # the shape score rises from 0 to 1 as the share of lower-body returns on vertical faces (two slices per axis) goes from the first to the second
MISSING_FACE_SHARE_ALL = {
    "Car": (0.4, 0.7)
}  # … for a cluster of these classes judged on all its returns (fewer than MISSING_FACE_MIN_LOWER lower-body returns): a car's cabin is set back from its body's ends and sides, off the body's faces
MISSING_FILL = (
    0.1,
    0.3,
)  # the density score rises from 0 to 1 as returns per ray over the cluster's angular extent go from the first to the second
MISSING_FILL_SAMPLES = 9  # points along each side of a visible rectangle facing the sensor, over which its returns per ray are integrated (each direction at its own range)
MISSING_HEADINGS = 90  # headings tried over [0, 90°) (1° steps)
MISSING_RATE_SAMPLE = 4096  # returns sampled to estimate the sensor's rays per steradian (elevation quantiles)
MISSING_MIN_DEPTH = 0.5  # m; KITTI: a candidate's centre must be this far in front of the camera
MISSING_MAX_TRUNCATION = 0.9  # KITTI: a candidate whose centre projects outside image_2 is one while at most this share of its 2D box lies outside (KITTI labels objects truncated up to ~0.9 by the image's edge)
MISSING_DONTCARE_OVERLAP = 0.5  # KITTI: a candidate whose 2D box lies this much inside a DontCare region is not one
MISSING_LABEL_IOU = 0.1  # a cluster or a detection is a candidate only with a BEV IoU below this to every label (one that overlaps a label more is that label's error)
MISSING_MERGE_IOU = 0.1  # a detection and a cluster overlapping this much (BEV IoU) are one candidate ("both")
MISSING_MIN_KEPT_SCORE = 0.05  # clusters scoring below this are not written (most of the frame's clutter)
MISSING_CLASS_SIZES = {  # classes the search looks for: (mean, largest) length, width, height in metres (KITTI / Waymo statistics)
    "Car": ((3.9, 1.6, 1.55), (5.3, 2.1, 2.1)),
    "Van": ((5.1, 1.9, 2.2), (6.5, 2.4, 3.0)),
    "Truck": ((10.1, 2.6, 3.25), (16.0, 3.0, 4.2)),
    "Vehicle": ((4.6, 2.0, 1.8), (6.5, 2.5, 2.8)),
    "REGULAR_VEHICLE": ((4.7, 1.95, 1.7), (6.5, 2.5, 2.6)),
}
MISSING_CLASS_MIN_TOP = {
    "Truck": 2.4
}  # m; classes whose roof is at least this high: the returns must reach it (or the highest beam there)
MISSING_CLASS_MIN_CORNER = {
    "Truck": (1.0, 1.5)
}  # m; classes seen only as an L-shape: the size score rises from 0 to 1 as the shorter leg (the rear or the front beside the side) goes from the first to the second (a stretch of wall has one face)
MISSING_CLASS_REAR_WIDTH = {
    "Truck": 2.2
}  # m; a face at least this wide (and no wider than the class's largest width) whose returns reach the class's roof (MISSING_CLASS_MIN_TOP, or the beams' reach) is that class seen from behind or ahead: no L-shape asked, and it is chosen over smaller classes (KITTI widths: Van 1.90 ± 0.12, Truck 2.58 ± 0.15 m; 2.2 m lies as many deviations from either)
MISSING_REAR_FILL = 0.7  # … and whose returns per ray over it (MISSING_FILL's measure) reach this: a truck's rear is one solid panel square to the rays (a building's front with windows or glass sends back a third)
MISSING_IMAGE_SLACK = 100.0  # px; KITTI: clusters whose centroid projects this far outside image_2 are not boxed (a candidate's centre must project inside)
MISSING_FRAGMENT_POINTS = 3  # components with fewer returns are not joined to others (noise)
MISSING_MERGE_GAP = (
    2.5  # m; a fragment this far behind another (range) in the same direction is the same object (rear face and cabin)
)
MISSING_MERGE_OVERLAP = 0.5  # … when their azimuth intervals overlap by this share of the narrower one
MISSING_POINTS_RAMP = (
    8,
    20,
)  # the density score also rises from 0 to 1 as the cluster's returns go from the first to the second (too few to tell)
MISSING_CONTINUATION = 3.0  # m; a face whose line goes on this far beyond the cluster through other unexplained returns is part of a longer structure (a wall)
MISSING_CONTINUATION_CELLS = 3  # … when at least this many cells along that extension hold such returns
MISSING_CONTINUATION_RUN = 1.0  # m; … spread along the extension over at least this length (a wall square to the face, behind it, crosses in less)
MISSING_TALL_MARGIN = (
    0.2  # m; an unseen top counts against a class only where the beams would pass this much over its mean height
)
MISSING_MERGE_SIDE_CELLS = 2  # fragments whose footprints come within this many cells of each other are one object too (a side broken by a dark panel or glass)
MISSING_ROW_CELLS = 2  # fragments of at most this many cells may be joined in a row (a truck's side at a grazing angle: one column of returns per azimuth step)
MISSING_ROW_GAP = 3  # … to another such fragment whose footprint comes within this many cells of theirs
MISSING_ROW_MIN = 3  # … when at least this many fragments form the row
MISSING_ROW_RESIDUAL = (
    0.25  # m; … and their centres lie this close to one straight line (a corner's second leg turns away)
)
MISSING_ROW_ANGLE = (
    30.0  # degrees; … that line runs within this of the sensor's ray to the row (the side is seen at a grazing angle)
)
MISSING_CORNER_DEPTH = 1.5  # m; a face is part of a larger structure too where other returns at one of its ends run this far away from the sensor, square to it (a building's corner)
MISSING_OWN_FRAGMENT_CELLS = 6  # a group of at most this many cells inside the box a cluster would become is its own far end or roof edge seen past a gap, not a wall going on (continuation test)
MISSING_CLASS_OWN_REACH = (
    "Truck",
)  # classes whose groups in line with their side within the class's largest length are their own (a truck's cab past the gap between cab and box, its far end past an occluder), not a wall going on (continuation test)
MISSING_CORNER_START = 0.6  # m; … and begin within this of the face (a building's end wall meets its front; a hedge behind a parked car begins beyond the car's width)
MISSING_REGION_SLACK = 3.0  # m; clusters whose centroid lies this far beyond the labelled range are not boxed (a box centre may lie farther than its returns)
MISSING_CLASS_FIT = (
    0.5  # a candidate resembles the smallest class whose size score reaches this (else the best-scoring one)
)
MISSING_FREE_SHARE = (
    0.1,
    0.4,
)  # the free-space score falls from 1 to 0 as the share of rays passing through the box's lower body goes from the first to the second
MISSING_PLACE_STEP = 0.25  # m; between the placements of a partly seen box's hidden extent that are tried
MISSING_PLACE_SPOT = 0.4  # m; between the spots of its footprint whose line of sight is tested
MISSING_PLACE_MIN_HIDDEN = (
    1.0  # m; a box is placed by what the sensor sees empty only when this much of its length or width is hidden
)
MISSING_PLACE_MARGIN = 1  # spots seen empty a placement must spare over the growth away from the sensor to replace it
MISSING_PLACE_RAY_MARGIN = 1  # free rays (each costing −log FREE_SPACE_SLIT_PROB) a placement of a partly hidden box must spare over the one grown by lines of sight to replace it
MISSING_LENGTH_SPREAD = 3.0  # a class's largest length lies this many standard deviations above its mean: the spread of the prior on a partly hidden box's length (KITTI: Car (5.3 − 3.9) / 3 = 0.47 m against 0.43 measured, Van 0.47 against 0.50, Truck 1.97 against 2.0)
MISSING_PLACE_MIN_SCORE = 0.5  # a partly hidden box is placed by the frame's rays only when its score before the free space reaches this (the free-space factor only lowers it; below it a candidate is not one a review reads: rank --missing --min-score 0.5, the benchmarks' threshold)
MISSING_PLACE_SIGHT_HEIGHT = 0.85  # a spot's line of sight aims at this share of the cluster's seen top (at most the class's mean height): a label lower than the line where it crosses does not hide the spot (the sensor sees over a parked car)
MISSING_REFINE = True  # the candidate's box is refined by the label-error fit (core/fit.py) before its rays are counted
MISSING_GROUND_RANK = (
    3  # a ground cell's floor is its this-lowest return (fewer returns below the road than this are ignored)
)
MISSING_GROUND_SHARE = 0.05  # … unless fewer than this share of the cell's returns lie within MISSING_BAND[0] above it (a layer under the road: its mirror image of a number plate or tail-light, a dozen returns of the hundreds near the sensor): then the return this share lie under
MISSING_GROUND_DROP = (
    1.5  # m; a ground cell's floor this far below the median of its 3 × 3 neighbourhood is stray returns, not the road
)
MISSING_GROUND_OPENING = 9.0  # m; ground narrower than this square is not ground (an opening of the ground grid): an object in an occluder's shadow or between a far object's sparse road rings is not taken for the road
MISSING_GROUND_OPENING_WIDE = 25.0  # m; … and where that square holds few cells with returns (a shadow), ground narrower than this square is not ground either
MISSING_GROUND_MIN_CELLS = (
    0.25  # share of the opening's square with returns under which the square is a shadow (the wider opening applies)
)
MISSING_SPLITS = 3  # a cluster that fits no class is split at a gap at most this many times (two cars side by side, a car and a hedge)
MISSING_SPLIT_BIN = 0.1  # m; slices across a cluster's axes in which a gap between two objects is looked for
MISSING_SPLIT_GAP = 0.1  # … a slice holding at most this share of the returns of an average occupied slice is a gap
MISSING_SPLIT_MIN_PART = 1.0  # m; … with at least this much of the cluster on either side of it
MISSING_SPLIT_MIN_POINTS = 10  # … and at least this many returns on either side
MISSING_CEILING_BINS = 360  # azimuth bins (1°) of the top beam's elevation (the sensor's tilt makes it vary around)
MISSING_BEAM_GAP = 0.4  # deg; elevation between two beams (HDL-64E 0.4°, Waymo TOP 0.3°): a far vehicle's highest return may lie this far under its top
MISSING_FORWARD_COS = 0.9  # a camera whose optical axis is this close to +x (cosine) looks forward: the search grid starts just behind the sensor
MISSING_CEILING_FLOOR = (
    -2.0
)  # deg; returns below this elevation are never a top beam's (the per-direction top beam looks only above it)
MISSING_CEILING_SPREAD = 1.5  # deg; the top beam in a direction is taken no lower than this under the frame's highest (a direction with open sky returns only lower beams)
MISSING_FACE_TIE = (
    0.1  # headings whose face share is within this of the best one tie; the tightest rectangle among them wins
)
MISSING_SURFACE_ROUGH = (
    0.035,
    0.06,
)  # m; the shape score is scaled from 1 to 0 as the median distance of a cluster's returns from the line of their neighbours along the beam goes from the first to the second (a car's body: the range noise, ~0.01–0.02; foliage: returns from anywhere in its depth)
MISSING_SURFACE_BEAM_GAP = 0.1  # deg; returns closer than this in elevation seen from the sensor are one beam's (HDL-64E beams are 0.33–0.5° apart)
MISSING_SURFACE_STEP = 1.0  # deg; a beam's neighbouring return farther than this in azimuth is on another surface
MISSING_SURFACE_MIN_RETURNS = 8  # a cluster with fewer returns between beam neighbours keeps its shape score

# --- KITTI (official object devkit, evaluate_object.cpp) ---
KITTI_IMAGE_SIZE = (
    1242,
    375,
)  # px; image_2's usual width, height: the labelled field of view when image_2/<frame>.png cannot be read
KITTI_MIN_HEIGHT = (40.0, 25.0, 25.0)  # Easy/Moderate/Hard: 2D box height must exceed this (pixels)
KITTI_MAX_OCCLUSION = (0, 1, 2)  # Easy/Moderate/Hard: largest allowed occlusion level (3 = unknown)
KITTI_MAX_TRUNCATION = (0.15, 0.30, 0.50)  # Easy/Moderate/Hard: largest allowed truncation fraction

# --- detector evaluation (labelaudit/evaluate, docs/eval.md) ---
EVAL_RECALL_POINTS = 41  # devkit N_SAMPLE_PTS: recall samples 0, 1/40, …, 1 (R40 averages the last 40, R11 every 4th)
EVAL_MIN_OVERLAP = {
    "Car": 0.7,
    "Pedestrian": 0.5,
    "Cyclist": 0.5,
    "Vehicle": 0.7,
    "REGULAR_VEHICLE": 0.7,
}  # the usual threshold per class: devkit MIN_OVERLAP (KITTI), Waymo's 3D-detection thresholds (their vehicle value for AV2's cars)
EVAL_DEFAULT_MIN_OVERLAP = 0.5  # usual threshold of a class not listed above
EVAL_MAP_THRESHOLDS = (
    0.5,
    0.55,
    0.6,
    0.65,
    0.7,
    0.75,
    0.8,
    0.85,
    0.9,
)  # mAP over localisation thresholds 0.5:0.05:0.9 (the paper's Table II)
EVAL_NEIGHBOUR_CLASSES = {
    "Car": ("Van",),
    "Pedestrian": ("Person_sitting",),
}  # devkit: GT of these classes is ignored (neither TP nor FN) when evaluating the key
EVAL_CLASSES = {
    "kitti": ("Car", "Pedestrian", "Cyclist"),
    "waymo": ("Vehicle", "Pedestrian", "Cyclist"),
    "av2": ("REGULAR_VEHICLE", "LARGE_VEHICLE", "BUS", "BOX_TRUCK", "TRUCK", "PEDESTRIAN", "BICYCLIST", "MOTORCYCLIST"),
}  # evaluated by default (those detected at least once, like the devkit)
EVAL_DISTANCE_BINS = (20.0, 40.0)  # m; mean overlaps per GT distance bin 0–20, 20–40, ≥ 40 m (the paper's Figs. 10–11)
EVAL_ASSOCIATION_MIN_IOU = 0.1  # a detection "localises" a GT (per-detection table, mean overlaps) when the devkit matching pairs them at IoU above this
EVAL_WAYMO_LEVEL2_MAX_POINTS = (
    5  # Waymo: GT boxes with at most this many LiDAR points are LEVEL_2 whatever their label says
)
EVAL_LET_WAYMO_CAMERA = (
    1.43,
    0.0,
    2.18,
)  # m, vehicle frame; Waymo's camera-only challenge measures range (LET) from here
EVAL_LET_AV2_CAMERA = (
    1.635,
    0.003,
    1.398,
)  # m, ego frame; Argoverse 2 ring_front_center as its sensor calibration (egovehicle_SE3_sensor) places it
EVAL_LET_TOLERANCE_FRACTION = (
    0.1  # LET: longitudinal tolerance as a fraction of the GT's range from the camera (Waymo's 10 %)
)
EVAL_LET_MIN_TOLERANCE = 0.5  # m; LET: the tolerance never falls below this (near objects)
EVAL_LET_MIN_IOU = dict.fromkeys(
    (
        "Car",
        "Vehicle",
        "Van",
        "Truck",
        "Bus",
        "Tram",
        "REGULAR_VEHICLE",
        "LARGE_VEHICLE",
        "BUS",
        "SCHOOL_BUS",
        "ARTICULATED_BUS",
        "BOX_TRUCK",
        "TRUCK",
        "TRUCK_CAB",
    ),
    0.5,
)  # LET-IoU a vehicle match needs (Waymo's camera-only challenge; KITTI, Waymo and Argoverse 2 vehicle names)
EVAL_LET_DEFAULT_MIN_IOU = 0.3  # LET-IoU every other class (pedestrians, cyclists) needs
EVAL_LET_SCORE_CUTOFFS = 101  # LET: score cut-offs 0, 0.01, …, 1 (a detection counts at cut-offs ≤ its score)
EVAL_LET_RECALL_DELTA = (
    0.05  # LET: AP integration pads the PR curve with a point every 0.05 of recall (Waymo's desired_recall_delta)
)
EVAL_LET_EPSILON = 1e-6  # m; LET: smallest range (a centre at the camera) — Waymo's kEpsilon
EVAL_LET_WEIGHT_SCALE = (
    1_000_000  # LET: Hungarian weights LET-IoU·a quantised to integers of 10⁻⁶, as Waymo's matcher (kMaxIoU)
)
EVAL_WORKER_PRELOAD = (
    "labelaudit.evaluate.warmup",
)  # eval's fork server: the JIoU kernels only (no Open3D), warmed once; several s less than WORKER_PRELOAD when the server starts

# --- sane ranges of label values (readers: labelaudit/datasets/base.py box_problems) ---
MIN_BOX_SIZE = (
    0.01  # m; a labeled length, width or height below this (0, negative, 1e-300) is corrupt input: an error row
)
MAX_BOX_SIZE = (
    200.0  # m; a labeled length, width or height beyond this is corrupt input (the label becomes an error row)
)
MAX_BOX_CENTRE = 1.0e4  # m; a box centre coordinate farther than this from the sensor is corrupt input
MAX_BOX_ANGLE = 1.0e3  # rad; |yaw| beyond this is corrupt input, not an angle (wrapping it loses its digits)

# --- Argoverse 2 (labelaudit/datasets/av2.py, docs/datasets.md) ---
AV2_LIDAR_MOUNTS = {
    "up_lidar": (1.35018, 0.0, 1.64042),
    "down_lidar": (1.34676, 0.00457, 1.52550),
}  # m; ego-frame lidar positions of the AV2 rig, used when a log has no calibration/ (the sensor origin is their midpoint)
AV2_QUATERNION_TOLERANCE = (
    1e-3  # a cuboid or pose quaternion whose norm differs from 1 by more than this is corrupt input, not a rounding
)
AV2_MAX_TILT = 0.01  # rad; a cuboid whose up axis leans more than this (roll/pitch) is audited upright with its heading, with a warning
AV2_ROI_MARGIN = 5.0  # m; AV2 labels within this of the drivable area (its region of interest: av2-api ROI_ISOCONTOUR_M); missing-label candidates must touch it

# --- accepted config values (labelaudit/config.py validate_params): key -> (low, high, low open?, high open?) ---
PARAM_RANGES: dict[str, tuple[float, float, bool, bool]] = {
    "model.sigma": (
        1e-4,
        10.0,
        False,
        False,
    ),  # m; LiDAR noise: 0.1 mm … 10 m (1e308 made every object fail, inf made every std the prior's)
    "model.num_nearest": (1, 6, False, False),  # M: a box has at most 6 faces (the core uses min(M, 2·dim))
    "model.outlier_prob": (0.0, 1.0, False, True),  # a probability; 1 would make every point an outlier
    "model.prior_weight": (1e-6, 1e6, False, False),  # w: beyond this the prior is numerically gone or absolute
    "model.min_points": (0, 2**31 - 1, False, False),  # a point count (int32 in the results)
    "spatial.cells_per_side": (8, 1024, False, False),  # JIoU grid; 1024² cells per box is already ~1 s
    "spatial.num_samples": (16, 65536, False, False),  # Sobol samples of φ per box
    "spatial.support_std": (0.0, 20.0, True, False),  # grid half-width in corner stds
    "spatial.seed": (0, 2**32 - 1, False, False),  # numpy / scipy seeds are unsigned 32-bit here
    "crop.margin": (0.0, 20.0, False, False),  # m
    "crop.ground_cut": (0.0, 20.0, False, False),  # m
    "crop.fit_margin": (0.0, 20.0, False, False),  # m (also ≥ margin)
    "prior.center": (1e-6, 100.0, False, False),  # m; prior std of the box centre
    "prior.length": (1e-6, 100.0, False, False),  # m
    "prior.width": (1e-6, 100.0, False, False),  # m
    "prior.height": (1e-6, 100.0, False, False),  # m
    "prior.yaw": (1e-6, 100.0, False, False),  # rad
    "missing.max_range": (1.0, 1000.0, False, False),  # m; the labelled range of a dataset
    "missing.min_points": (3, 2**31 - 1, False, False),  # a box needs 3 points
    "missing.detection_min_score": (-1e9, 1e9, False, False),  # detector confidences are any finite number (logits too)
}

# --- classes ---
DEFAULT_CLASSES = ("Car", "Van", "Truck")  # vehicles: the paper's evaluation classes


# Prior std per class (metres, radians), before the weight w.
DEFAULT_PRIORS: dict[str, dict[str, float]] = {
    # KITTI car, from the authors' code (x_std of uncertain_label_3D): centre 0.25 m per axis,
    # l 0.44, w 0.10, h 0.10, yaw 0.1745 rad (10°). the paper's design notes round width to 0.11; the code wins (docs/method.md).
    "default": {"center": 0.25, "length": 0.44, "width": 0.10, "height": 0.10, "yaw": 0.1745},
    # Not in the paper: people and bikes are small, and their heading is harder to annotate.
    "Pedestrian": {"center": 0.10, "length": 0.10, "width": 0.10, "height": 0.10, "yaw": 0.50},
    "Cyclist": {"center": 0.15, "length": 0.20, "width": 0.10, "height": 0.10, "yaw": 0.25},
}

# --- simulator (labelaudit/sim, docs/simulator.md) ---
SIM_SENSOR_HEIGHT = 1.73  # KITTI Velodyne height above the ground (m); ground is z = -1.73 in the LiDAR frame
SIM_BEAMS = 64  # HDL-64E-like: number of laser rows in the range image
SIM_INCLINATION_DEG = (2.0, -24.8)  # top and bottom beam elevation (deg), KITTI's HDL-64E field of view
SIM_COLUMNS = 2118  # azimuth columns per sweep: 360°/2118 ≈ 0.17° step, ~120k returns per frame
SIM_RANGE_LIMITS = (1.0, 120.0)  # returns closer/farther than this (m) are dropped, like the real sensor
SIM_RANGE_NOISE = 0.02  # std of the Gaussian range noise (m), the HDL-64E datasheet accuracy
SIM_DROPOUT = (0.02, 0.10)  # missing-return probability: base, plus this much more at max range (∝ r²)
SIM_NUM_VEHICLES = (5, 25)  # vehicles per frame, drawn uniformly (inclusive)
SIM_NUM_VRU = (0, 4)  # pedestrians + cyclists per frame, drawn uniformly (inclusive)
SIM_DISTANCE = (5.0, 70.0)  # object centre distance from the sensor (m), drawn uniformly
SIM_FRONT_FRACTION = 0.7  # share of objects placed inside the camera's field of view (KITTI labels only there)
SIM_ROAD_ALIGNED_FRACTION = 0.6  # share of objects heading along the road axis (yaw ≈ 0 or π); the rest uniform
SIM_OCCLUSION_LEVELS = (0.1, 0.5)  # occluded-ray fraction limits for KITTI occlusion levels 0 / 1 (else 2)
SIM_IMAGE_SIZE = (1242, 375)  # KITTI image width, height (px) for 2D boxes, truncation and the FOV test
SIM_VAL_FRACTION = 0.5  # share of simulated frames listed in ImageSets/val.txt (KITTI: 3769 of 7481)
SIM_MIN_NOISY_SIZE = 0.2  # perturbed box sizes are clipped to at least this (m), so labels stay valid
SIM_BENCH_NOISE = (0.3, 0.2, 0.1)  # label-error benchmark jitter: centre std (m), size std (m), yaw std (rad)
SIM_BENCH_FRACTIONS = (0.2, 0.02)  # label-error benchmark: jittered share, gross-error share of vehicle labels
SIM_GROSS_SHIFT = 1.0  # gross "shift" error: box centre moved this far (m) in a random BEV direction
SIM_MAX_TRUNCATION = 0.9  # objects whose 2D box is truncated more than this are outside the camera FOV (not labelled)
SIM_MAX_LABEL_OCCLUSION = 0.9  # objects with more of their LiDAR rays blocked than this are not labelled (unseen)
SIM_FOLIAGE_DEPTH = 0.3  # m; mean (exponential) depth a LiDAR ray enters simulated foliage before it returns
SIM_FOLIAGE_GAP = 0.25  # share of the rays into simulated foliage that pass through its gaps (no return from it)
SIM_CLUTTER = (4, 12)  # --clutter: unlabelled walls, poles and bushes per frame (min, max)
SIM_CHASSIS_CLEARANCE = {  # m; open height under a simulated vehicle's body, drawn uniformly per vehicle (--under-chassis); real KITTI: rays cross cars' boxes up to ~0.3 m, a truck's up to ~1 m
    "Car": (0.15, 0.3),
    "Van": (0.15, 0.3),
    "Truck": (0.4, 0.9),
}
SIM_TRACK_NOISE = (
    0.03,
    0.03,
    0.02,
    0.02,
)  # ordinary per-frame label noise inside tracks (std): centre per axis (m), length (m), width (m), yaw (rad) — must not be flagged
SIM_TRACK_ERROR_FRACTION = (
    0.05  # share of vehicle object-frames of a simulated sequence with one injected annotator error
)
SIM_TRACK_ERRORS = {
    "length": (0.25, 0.5),
    "width": (0.15, 0.3),
    "yaw": (0.1, 0.25),
    "centre": (0.3, 0.6),
}  # magnitude ranges (m, rad) of the injected errors (plus "flip": π)
SIM_MOVING_FRACTION = 0.5  # share of vehicles of a simulated sequence that drive (the rest are parked)
SIM_MOVING_SPEED = (3.0, 12.0)  # m/s, speed of a driving vehicle, drawn uniformly
SIM_MOVING_YAW_RATE = 0.25  # rad/s; a driving vehicle turns at a rate drawn uniformly in ± this
SIM_DET_CENTER_STD = 0.07  # synthetic detector (labelaudit/sim/detector.py): centre error std near the sensor (m)
SIM_DET_SIZE_STD = 0.04  # synthetic detector: length/width/height error std near the sensor (m)
SIM_DET_YAW_STD = 0.02  # synthetic detector: yaw error std near the sensor (rad)
SIM_DET_RANGE_SCALE = 40.0  # m; the synthetic detector's error stds double at this distance
SIM_DET_MISS = (0.05, 0.6)  # synthetic detector: miss probability of an object with ≥ / < SIM_DET_FEW_POINTS returns
SIM_DET_FEW_POINTS = 10  # synthetic detector: objects with fewer LiDAR returns are hard to detect
SIM_DET_FALSE_POSITIVES = 9.0  # synthetic detector: mean background false positives per frame (mostly low scores, like a detector's raw output)
SIM_DET_DUPLICATES = 0.1  # synthetic detector: share of detections with a shifted, lower-scoring duplicate
SIM_DET_VAN_AS_CAR = 0.3  # synthetic detector: probability that a Van is reported as a Car (else missed)

# --- product loop: infer / results (labelaudit.infer) ---
DEFAULT_RESULTS_DIR = "labelaudit-results"  # default -o/--output of `labelaudit infer`
CHUNK_UNITS = {
    "kitti": 16,
    "waymo-v2": 1,
    "waymo-v1": 1,
    "av2": 1,
}  # most units per shard: 16 KITTI frames, 1 Waymo segment (~200 frames), 1 Argoverse 2 log (~150 frames)
TARGET_CHUNKS = 32  # small runs are cut into about this many chunks (≥ 1 unit each) so workers stay balanced
MALLOC_MMAP_THRESHOLD = (
    32 * 2**20
)  # bytes (glibc's documented maximum on 64-bit); blocks below this come from the reused heap, not a fresh mmap each (per-box arrays of a few MB paid page faults on every box)
MALLOC_TRIM_THRESHOLD = (
    64 * 2**20
)  # bytes; glibc: free heap kept for the next box up to this much, instead of returned to the system after each
POOL_START_METHOD = "forkserver"  # workers fork from a clean, single-threaded server (not from the busy main process)
WORKER_PRELOAD = (
    "labelaudit.infer.run",
    "labelaudit.infer.crop",
    "labelaudit.infer.rows",
    "labelaudit.infer.warmup",
)  # imported once in the fork server (and by each Dask worker at start): the core, its compiled kernels (Open3D only loads where a crop asks it)
DASK_LOCAL_CONFIG = {
    "distributed.worker.profile.enabled": False
}  # a LocalCluster's workers run without Dask's statistical profiler (a stack sample of the task thread every 10 ms: 5–10 % of a `local:2` run here)
DASK_CONNECT_TIMEOUT = 10.0  # s; an unreachable --scheduler is reported after this long (exit 2)
DASK_WORKER_WAIT = 60.0  # s; a scheduler without workers is reported after this long (a cluster that is still scaling up gets this much)
DEFAULT_GATE_CONFIG = "gate.toml"  # built-in thresholds of `labelaudit check` (labelaudit/configs/)
DEFAULT_RANK_TOP = 20  # rows shown by `labelaudit rank`
DEMO_FRAMES = 12  # simulated frames of `labelaudit demo`: a few hundred objects, seconds on 2 cores
DEMO_DROP_FRACTION = (
    0.1  # share of vehicle labels the demo's simulator leaves out: missing labels for the search to find
)
DEMO_MISSING_SCORE = 0.5  # the demo lists missing-label candidates at or above this score
DEMO_REPORT_NAME = (
    "labelaudit-demo-report.html"  # where `labelaudit demo` without FOLDER writes its report (the current folder)
)

# --- export: training targets (labelaudit.training / labelaudit.export, docs/training.md) ---
HEURISTIC_NUM_POINTS_HALF = (
    10.0  # "num points" source: the prior variance halves at this many points (var = prior · n0/(n0+n))
)
HEURISTIC_HULL_IOU_FLOOR = (
    0.01  # "hull_iou" source: var = prior · max(1 − IoU, this), so a perfect hull never claims zero variance
)
DEFAULT_ANCHOR_SIZES: dict[str, dict[str, tuple[float, float, float]]] = {
    # l, w, h (m) of the anchors OpenPCDet's KITTI configs (second.yaml, pointpillar.yaml) and
    # mmdetection3d's pointpillars_hv_secfpn_kitti ship; only the sizes enter the residual's variance.
    "kitti": {"Car": (3.9, 1.6, 1.56), "Pedestrian": (0.8, 0.6, 1.73), "Cyclist": (1.76, 0.6, 1.73)},
    # OpenPCDet's waymo_models/second.yaml anchors.
    "waymo": {"Vehicle": (4.7, 2.1, 1.7), "Pedestrian": (0.91, 0.86, 1.73), "Cyclist": (1.78, 0.84, 1.78)},
}
EXPORT_GLENET_MISSING = (
    -1.0
)  # GLENet value of an object without label variances (its own converter writes -1 for classes its CVAE did not see)
EXPORT_GLENET_MIN_VARIANCE = (
    1e-10  # floor of an exported GLENet variance: its loss takes log(v + 1e-10), so a value is never below that offset
)
INFOS_DIMENSION_TOLERANCE = 1e-3  # m; an infos object whose l/w/h differ from the result row's by more is a mismatch
EXPORT_REVIEW_LABEL_ERROR = 0.5  # `export --format kitti-labels`: labels with label_error above this get their suggested box (a reviewer dismisses a wrong one in seconds, so lower than the gate's 0.9)
EXPORT_REVIEW_TRACK_ERROR = 0.5  # `export --format kitti-labels` (Waymo, AV2): labels with track_error above this get the box their track expects (where the label is likelier wrong than right; lower than the gate's TRACK_FLAG for the same reason as EXPORT_REVIEW_LABEL_ERROR)
EXPORT_REVIEW_MIN_SCORE = 0.5  # `export --format kitti-labels`: missing-label candidates with a score of at least this are added (the score where a missed object is likelier than not)
EXPORT_REVIEW_IMAGE_SIZE = (
    1242,
    375,
)  # pixels; the image_2 size the 2D boxes of added lines are clipped to when the frame's PNG is not there (KITTI's usual size)
INFOS_PICKLE_PROTOCOL = (
    4  # pickle protocol of written infos copies: loads on every Python 3 that OpenPCDet/mmdet3d support
)

# --- pictures and the review report (labelaudit/viz, docs/review.md) ---
VIZ_DPI = 100  # matplotlib dots per inch of every picture: figure size = pixels / this
VIZ_NEAREST_IDS = 5  # an unknown frame/object id lists this many nearest valid ids
VIZ_FRAME_CACHE = 8  # frames kept in memory while a gallery renders (several pictures per frame)
SHOW_SIZE = (640, 600)  # default `show` picture of one object, width × height in pixels
SHOW_FRAME_SIZE = (1000, 800)  # default `show` picture of a whole frame, pixels
SHOW_MAX_POINTS_DRAWN = 1500  # a denser crop is drawn with an even subsample (same look, bounded drawing time)
SHOW_CONTEXT_MARGIN = 2.0  # m; points this far around the box are drawn (grey) for orientation
SHOW_VIEW_MARGIN = 0.8  # m of free space around the label, suggested box and 2-σ corner ellipses
SHOW_TRACK_FRAMES = (
    3  # `show` of a tracked object draws its labels in this many frames before and after (moved into this frame)
)
SHOW_FRAME_WORST = 5  # `show` of a frame numbers this many worst boxes
SHOW_FRAME_MARGIN = 6.0  # m around the frame's boxes (and the sensor) in the frame picture
SHOW_CANDIDATE_MARGIN = (
    2.5  # m around a missing-label candidate in its close-up (enough to see a neighbouring label or wall)
)
SHOW_MISSING_MIN_SCORE = (
    0.5  # `show` of a frame draws the missing-label candidates with at least this score (--min-score)
)
REPORT_TOP = 12  # default gallery size per ranking of `labelaudit report`
REPORT_GALLERY_SIZE = (520, 480)  # gallery pictures, pixels (smaller than `show`'s: the HTML stays light)
REPORT_PLOT_SIZE = (620, 400)  # aggregate plots, pixels
REPORT_DISTANCE_BIN = 10.0  # m; Fig. 7b bins of the distance to the sensor
REPORT_LOG_POINTS_BIN = 0.25  # Fig. 7c bins of log10(number of points)
REPORT_MIN_BIN_COUNT = 3  # a plot bin with fewer objects is not drawn (its mean is noise)
REPORT_MAX_ERROR_ROWS = 50  # failed frames listed in the report (the rest are counted)
REPORT_MISSING_MIN_SCORE = 0.5  # `labelaudit report`: candidates with at least this score are counted and pictured
REPORT_AP_INTERP = "R40"  # AP interpolation shown in the report table (KITTI's official since 2019)

# --- what the parameter hash leaves out (labelaudit.config.constants_digest) ---
# Numbers that never change a row of `infer`: the simulator, pictures and reports, exports, detector
# evaluation, CLI defaults and scheduling. Changing them never blocks `--resume`; every other
# upper-case name of this module is hashed (a new one is hashed unless it is listed here).
UNHASHED_PREFIXES = (
    "SIM_",
    "VIZ_",
    "SHOW_",
    "REPORT_",
    "EXPORT_",
    "EVAL_",
    "DEMO_",
    "HEURISTIC_",
    "INFOS_",
    "DEFAULT_ANCHOR_",
    "DASK_",
    "UNHASHED_",
)
UNHASHED_NAMES = frozenset(
    {
        "DEFAULT_RESULTS_DIR",
        "CHUNK_UNITS",
        "TARGET_CHUNKS",
        "POOL_START_METHOD",
        "MALLOC_MMAP_THRESHOLD",
        "MALLOC_TRIM_THRESHOLD",
        "WORKER_PRELOAD",
        "DEFAULT_GATE_CONFIG",
        "DEFAULT_RANK_TOP",
        "PARAM_RANGES",
        "CROP_GRID_MIN_BOXES",
        "CROP_GRID_CELL",
        "CROP_GRID_BATCH",
        "CROP_GRID_DENSE_CELLS",
    }
)  # ranges only refuse a config; the grid crop gives Open3D's indices
