"""Common-motion grouping of features into vehicles (incremental pair graph, connected components).

A pair is linked when first seen together within the connection distance (or later, for the few features of
a lone vehicle) and dismissed when its distance range over the common interval exceeds the segmentation
threshold (TI/Beymer style).
A new group that is part of a known vehicle (its roof, projected further and faster) joins it; a
reported one is watched for RECHECK_S more and joins once it keeps one place on a vehicle. A part beyond what
is seen of its vehicle joins only where the image between the two is one body.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from numba import njit

from appliance.config import TrackingParams
from appliance.types import NO_VEHICLE, VehicleState
from appliance.zones import SiteZones

UNSEEN, LINKED, APART = 0, 1, 2
# a fragment joined to its vehicle for good: MERGED_LO when the pair's lower slot is the fragment's, MERGED_HI
# when the higher one is
MERGED_LO, MERGED_HI = 3, 4
# same lane, too far apart when first seen together: they may still link (see LATE_BESIDE_M)
FAR = 5
SETTLED_AGE = 5  # frames before a feature's speed counts
# The vehicles in view when the grouper starts (the service started, or a config reload rebuilt the pipeline) show at
# first only the corners the tracker finds in its second frame (the first gives none), often a roof's rear edge, and
# their groups form before those features settle: such a near end, up to 10 m behind the front 45 m from the camera,
# reads a vehicle that crossed its count line before the start as short of it, and its first steps would count it.
# A first report carries no near-end points from before the grouper's step START_SETTLE_STEPS (Grouper.settled_t,
# when the features found in its second step are SETTLED_AGE - 1 frames old): it counts only what crossed since. (Its
# own state and those after it are from that step on while tracking.min_track_frames is 5 or more.) On the
# synthetic scenes 12 of the 16 crossings counted in a scene's first 0.2 s were such vehicles; this drops 11 of them
# and the 4 true crossings (fronts 2-5 m short of the line at the start: seen alike).
START_SETTLE_STEPS = SETTLED_AGE + 1

# A feature's motion when a pair is first seen: STANDING below STANDING_MPS once settled (scenery, an
# occluder's edge, a queued vehicle), MOVING above MOVING_MPS, else unsure (0)
STANDING, MOVING = 1, 2
STANDING_MPS = 1.0
MOVING_MPS = 4.0
# A vehicle's lowest point in the image is its least magnified by height (bumper, grille): a settled feature lower
# in the image than the rest of its group that moves over REP_FAST_K times the median speed of the group's settled
# features (4 or more) in projection is not its near end but a part of the vehicle ahead (its roof's rear edge),
# linked to the group through a corner between the two; taken for the near end it drags the vehicle's near end
# ahead and speeds it up. Only from a median of REP_FAST_MIN_MPS (see PART_MIN_MPS: in a crawl a speed ratio says
# little). (On the synthetic scenes: lane-periods with the speed within 2.5 % from 43 to 46 of 54, count-line
# misses and extras 488 to 471.)
REP_FAST_K = 1.08
REP_FAST_MIN_MPS = 10.0
NEAR_REP_M = 3.0  # features this close along the road to the representative one give the velocity
# ... and those this close its spot speed, reported at count lines, presence loops and in vehicle records: the
# lowest on the vehicle (bumper, grille). A feature at height h moves H / (H - h) times as fast in projection as
# the road under it (camera height H); the NEAR_REP_M band takes in lights and bonnet too and reads 2-5 % fast.
SPOT_M = 1.0
MIN_TRAVEL_M = 1.0  # a group is reported once it has moved this far (static texture never does)
MIN_SPEED_MPS = 1.5  # ... and is moving at least this fast (vehicles are found while they move)
# At night (Grouper.lights_only) a vehicle is seen by its lights alone: a group one feature short of
# TrackingParams.min_features (a motorcycle's one headlamp) is a vehicle once it has held together this long
# over this distance (by day such groups are mostly parts of vehicles that have yet to join them)
SMALL_S = 1.0
SMALL_M = 5.0
# A group not yet reported whose near end has stood still this long (within STILL_M) starts its trajectory
# afresh, also after it moved a little: features on an occluder's edge where vehicles emerge (dragged a
# metre by the vehicle that passed behind it, then stuck), joined by the next vehicle once it comes out,
# must not date that vehicle's entry back to when the edge was first seen
STILL_S = 0.4
STILL_M = 0.5
# A reported group standing still this long that a vehicle of its lane then drives through is clutter
# (features left on an occluder's edge): vehicles queue, they do not pass through one another.
STALL_S = 2.0
# A reported group whose speed falls from MOVING_MPS to STANDING_MPS within this long, none of its features
# moving any more, has lost its vehicle: braking that hard would take 15 m/s^2. Its moving features went (lost,
# or the vehicle drove out from under them) and the ones left stand on the road; kept, it would stand in its
# lane adding time and no distance. (While some still move, the group may be clutter that a vehicle's new
# features just joined, low in the image where it enters: they carry on as the vehicle.)
DEAD_STOP_S = 0.2
# ... or whose near end came to stand (within STILL_M, in the last STALL_S) straight from DEAD_NEAR_MPS over the
# DEAD_STOP_S before, its features standing by now: braking from 8 m/s a vehicle still runs 4 m, and its next
# lowest feature would have moved the near end on. (The features left on an occluder's edge as the vehicle
# drove out from under it may take a second to read standing: their filter smooths the stop.)
DEAD_NEAR_MPS = 8.0
PASS_X_M = 1.5  # ... the vehicle passing within this much across the road
# A new group is a fragment of a known vehicle (its elevated top or its rear, seen as a separate group)
# when, after undoing the height magnification, its near end lies in that vehicle's footprint:
FRAGMENT_X_MARGIN_M = 0.5  # lateral slack around the footprint
FRAGMENT_X_MARGIN_NO_CAMERA_M = 2.0  # ... for elevated parts when the camera position is unknown
LEVEL_K = 1.05  # a part at most this much faster than its vehicle (in projection) is level with it: no height
# magnification to undo, and it joins at once (a faster one is an elevated part, watched first: WATCH_S)
MIN_LENGTH_M = 4.5  # the footprint reaches at least this far behind the vehicle's front (shortest car)
# An elevated part (its height undone) may lie anywhere over a vehicle up to this long and this wide (the
# longest and widest allowed on the road), beyond what is seen of the vehicle low down, where the image between
# the two is one body: the features seen low on a truck are often its cab alone, its box's top a group of its
# own that a camera beside the road sees over the next lane. (A faster vehicle in the next lane or behind looks
# the same in projection; the road between the two in the image tells them apart.)
ELEVATED_LENGTH_M = 18.75
ELEVATED_WIDTH_M = 2.6
# The camera's foot is known as well as the calibration's along-road scale, which may rest on assumed marking
# standards (up to 25 % out): undoing a height magnification k places a part up to this share of
# (1 - 1/k) times its distance from the foot off (see _elevated_parts)
FOOT_UNCERTAINTY = 0.25
# A reported group moving like an elevated part of a bigger reported vehicle (see Grouper._elevated_parts) is not
# kept apart from it: on real footage a car's roof and its body are often reported apart (a long lens magnifies
# heights: 1.2 times for a roof under an 8 m camera, its group 14 m behind the bumpers' at 60 m), and a feature
# found between them is the link that makes them one. Only while the vehicle moves at least this fast (36 km/h):
# at low speeds a speed ratio says little of height, and vehicles in a queue or in stop-and-go traffic must stay
# apart. (It costs the synthetic scenes 1-2 vehicles in four of 54 lanes, followers closing in on a car; from
# 5 m/s it cost the shockwave scenes up to 4 a lane.)
PART_MIN_MPS = 10.0
GHOST = -1  # host id meaning "a vehicle finalised in the last GHOST_S seconds" (its leftovers)
GHOST_S = 2.0
# ... and so is a group of its lane, new or reported less than RECHECK_S ago, that moves like an elevated part of
# one that left the view in the last GHOST_S at ADOPT_MIN_MPS or faster (over LEVEL_K times its speed, or
# RECHECK_K_MIN for a reported group as for any re-check, up to k_max) and, the camera known, lies on it with that
# height undone, as far as the longest vehicle reaches from its near end: a truck's or bus's top, projected tens of
# metres behind that end, is still in view after the end left the image (its group held the front alone, the top
# too far from it to link). Its last state names that vehicle, whose Edie time and distance it was. Only a vehicle
# that left the view: one finished when its features were lost may be found again as a new group, where its top
# would lie. Only in its lane: a faster car overtaking in the lane beyond lies in projection just where such a top
# would (on trucks-and-buses seed 14 four were lost when the lane beyond was allowed). In its lane a follower
# closing in fast just behind the vehicle as it leaves still looks like its top (no image test is left to ask).
# A new group that would join a vehicle as an elevated part (moving faster in projection) is watched first: a
# faster follower closing in behind looks just the same until one of the two changes speed (congestion).
WATCH_S = 1.0  # watched this long, unreported (followers' speed ratios change 10-25 % in a second of braking)
WATCH_MIN_HITS = 5  # ... and it joins after matching the vehicle in this many frames ...
WATCH_K_DRIFT = 0.1  # ... if its speed ratio held within this share (parts: within 2-8 %)
WATCHING = -2  # host id meaning "still watched"
# Only a tall vehicle's top is seen over the next lane, and a tall vehicle is long: beside a vehicle shorter in
# projection (its own_length) than SIDE_TALL_HOST_M, a group of the next lane that its height undone puts on that
# vehicle's footprint is its part only where the image between the two is its body (Grouper._host_of), at any speed.
# A car closing in on one in the next lane at a steady speed ratio lies just where such a part would. (On the
# synthetic scenes 43 missed crossings of vehicles seen at their count line had their features in a vehicle of the
# next lane, placed there as its part; asking the image beside short vehicles too, the misses seen at the line fell
# by 6, the lanes' count errors summed 8 fewer over both seed pairs, missed plus extra crossings 2 more.)

# A new group is first judged on its features' speeds, a frame or two old (one frame of image motion each): a
# roof's 15-20 % over its vehicle's speed may not show yet. When its speed is within UNSURE_K times a vehicle's
# and some height would put it on that vehicle, with the image between the two one body, it is watched before
# it is reported (see Grouper._unsure_host) and judged on its ratios and matches from when it is WATCH_SETTLE_S old.
# Only vehicles at PART_MIN_MPS or faster, and of another lane only tall ones (SIDE_TALL_HOST_M): a car's roof is
# not seen over the next lane.
UNSURE_K = (0.85, 1.3)
WATCH_SETTLE_S = 0.4
# a reported vehicle lost short of its exit (stopped in a queue, occluded) may be found again as a new group:
# within this long, and within this far of where it could be by then, a new group has not entered the view
# (see _entered). Lost at speed it has driven on at least as far as braking at LOST_BRAKE_MPS2 takes it.
LOST_KEEP_S = 60.0
REFOUND_M = 6.0
LOST_BRAKE_MPS2 = 8.0
# ... and its near end no faster when reported than accelerating at LOST_ACCEL_MPS2 from the lost one's speed
# takes it over the distance between (its near end may lie REFOUND_M behind the lost one's; plus
# LOST_SPEED_SLACK_MPS for a young group's speed): a group on clutter where a slow one was lost, taken over by
# a vehicle passing at speed, is that vehicle entering; taken for the lost one, it was never extended back to
# its region's entry.
LOST_ACCEL_MPS2 = 4.0
LOST_SPEED_SLACK_MPS = 3.0
# A vehicle lost within this long of its report (before the pipeline would release its first report: HOLD_S) is
# remembered only for being found again past its count line (see Grouper._entered): most are groups on clutter
# that a passing vehicle's features moved for a moment, over and over at the same spot (where vehicles come out
# from under an overhead sign's edge: one every few seconds, each holding off for LOST_KEEP_S every vehicle
# first seen there).
LOST_MIN_REPORTED_S = 0.5
RECHECK_S = 1.5  # a reported group is re-checked for being a fragment of another vehicle this long
RECHECK_VOTES = 10  # ... and joins a vehicle only after matching it in this many frames (a frame without a
# match is no evidence: the image's shadow test and the groups' extents flicker)
RECHECK_DRIFT_M = 1.5  # ... at a steady place on it (this much drift: a separate vehicle overtaking)
# ... as an elevated part at least this much faster (roof fragments: 1.15-1.5; a receding vehicle's speed
# may read a few per cent low, and a level part is a queued car's business)
RECHECK_K_MIN = 1.12
# A part still gathering votes when it or its vehicle leaves the view (the exit zone, near the image's edge, comes
# before RECHECK_VOTES frames) is taken as that vehicle's if it had matched it this many frames at a steady place,
# the last this recently:
ORPHAN_VOTES = 3
ORPHAN_GAP_S = 0.2
# A reported group that lay at k times a reported vehicle's distance from the camera's foot plus a constant
# (RIGID_K: an elevated part of it, seen beyond its near end) within RIGID_RES_M over the last RIGID_S, while
# that vehicle's speed changed by RIGID_DV_MPS or more, is that vehicle's part, at any speed: a follower
# through a stop or a start lags its leader by a second or more. (Checked every RIGID_EVERY frames; a roof
# reported apart in stop-and-go traffic otherwise adds its time to Edie's and stands on loops on its own.)
RIGID_S = 4.0
RIGID_DV_MPS = 4.0
RIGID_RES_M = 0.2
RIGID_K = (1.04, 1.5)
RIGID_EVERY = 10
# A group too small to be reported that lay, over the last ADOPT_S, at k times a reported vehicle's distance from
# the camera's foot plus a constant (k from ADOPT_K_MIN: high on it; within ADOPT_RES_SHARE of its own distance,
# as a pixel spans more road further away) while that vehicle travelled ADOPT_TRAVEL_M or more, lying on it with
# that height undone, its speed now k times the vehicle's (within ADOPT_K_TOL), and the image between the two one
# body, is a part of that vehicle: the few corners found on a bus's or a truck's top lie too far from its front in
# projection to link with it, and they show how long it is (checked every ADOPT_EVERY frames of the group, so that
# the length reaches the loops before the vehicle does). A follower closing in moves like a part only up to the
# speed difference of traffic in one lane, below ADOPT_K_MIN; one keeping its distance looks like a part of a long
# vehicle (its top at k over its leader's, a constant further on), and only the road seen between the two tells
# them apart. Hence only while the vehicle moves at ADOPT_MIN_MPS or faster: followers then keep a gap of 15 m or
# more (a second's headway), longer than what a car hides of the road behind it 45 m from a 10 m pole (8 m); in
# slower traffic a follower's top is seen right over the car ahead, as a long vehicle's would be. So in slower
# traffic an elevated part seen in another lane than its vehicle (Grouper._host_of) is its part only where the image
# between the two is its body, also when its height undone puts it on the footprint seen: in congestion the lanes
# move at different speeds, and a car closing in on one ahead in the next lane (its speed 1.3-1.8 times the
# other's) lies in projection where that car's top would at that height (on the shockwave scenes their lane-1 cars
# were counted 7-9 short, joined to lane-2 cars). At any speed beside a vehicle short in projection: see the note
# before UNSURE_K.
ADOPT_MIN_MPS = 15.0
ADOPT_S = 2.0
ADOPT_K_MIN = 1.1
ADOPT_K_TOL = 0.1
ADOPT_RES_SHARE = 0.008
ADOPT_TRAVEL_M = 5.0
ADOPT_POINTS = 10
ADOPT_EVERY = 5
ADOPT_JOINED_SHARE = 0.95  # of the image between the two differing from the road (a follower's gap shows)
# A part placed further back than a van is long is only a long vehicle's if it is as high as a truck's or bus's body:
# a follower's bonnet or roof (a car's 1-1.6 m up, a van's nearly 2 m) keeping its distance moves just like a part
# of the vehicle ahead there, whose roof hides the road between the two from the image test
ADOPT_FAR_M = 6.0
ADOPT_FAR_MIN_HEIGHT_M = 2.0
# A group found off the lanes (see Grouper.lifted) is adopted only as a top at least this high: a truck's, bus's or
# artic's box (3-4.5 m), above any car's or van's roof. Off the lanes a follower's roof is seen as well, right
# over a tall vehicle ahead that hides the road between the two; taken for that vehicle's top it made the
# vehicle as long as the gap and its footprint swallowed the follower.
LIFTED_TOP_M = 2.8
LIFTED_LANES = 1000  # lane labels of features found off the lanes, for the pair graph (see Grouper.lifted)
SPEED_WINDOW_S = 0.5  # speeds compared for the height magnification are taken over this long (see steady_vy)
# Reported length: each feature's place on the road behind the near end, from a straight-line fit of its
# projected distance from the camera's foot against the near end's over its life in the group (slope: its
# height magnification k; far steadier than one frame's speed ratio), once it has travelled enough with it
FIT_FRAMES = 10
FIT_TRAVEL_SD_M = 1.5  # standard deviation of the near end's distance over the fit (a 5 m travel at least)
# The far end is the furthest fitted feature with another this close (a lone one further out is mostly a
# misfit: a feature that slid along an edge, or one on the road in the vehicle's shadow)
FIT_NEIGHBOUR_M = 1.0
# A vehicle measured longer than the longest one with the along-road scale at its most out is two or more run
# together (a follower linked to it through corners found between the two): where a fitted feature lies that far
# behind its near end on the road, it is cut at the widest gap of at least SPLIT_GAP_M between its fitted features'
# places that leaves a vehicle's worth of them on each side and no more than LONGEST_M in front, if the part behind
# keeps up with the near end (the median of its fits' slopes at least 1 - SPLIT_LAG: a follower falling back is
# parting from it anyway). Its other features go with the fitted one nearest them, its shadow and its tops seen
# off the lanes stay with it. The part behind loses the vehicle's id and its links across the cut, new corners do
# not link the two again while the vehicle is a settled one (see _components), and the part never joins that
# vehicle as a fragment: it becomes a vehicle of its own.
LONGEST_M = ELEVATED_LENGTH_M * (1.0 + FOOT_UNCERTAINTY)
SPLIT_GAP_M = 2.0
SPLIT_LAG = 0.05
CUT_OWNER = 1 << 40  # (unbridge's owner of a part cut off vehicle v: CUT_OWNER + v)
# A vehicle none of whose fitted features lies this far behind its near end shows nothing of its extent (at
# night only its lights and their beam on the road ahead): it is reported at a typical car's length.
FIT_MIN_EXTENT_M = 0.5
NOMINAL_LENGTH_M = 4.5
# ... as is one measured shorter than the shortest car whose low part is wider than a motorcycle with its rider
SHORTEST_CAR_M = 3.0
SINGLE_TRACK_MAX_WIDTH_M = 1.2
# The far end seen is a roofline, not the bumper: a car's windscreen top lies about a third of its length
# behind its front (the bonnet is hidden from behind), its rear window's top about a sixth ahead of its rear.
HIDDEN_SHARE_FRONT = 0.3
HIDDEN_SHARE_REAR = 0.15
# ... but a far end fitted no higher than this is the vehicle's lowest edge (its bumper, or the edge of its shadow
# on the road beyond it): nothing of the vehicle lies beyond it. (Taken for a roofline, such a far end read 18 %
# long: on dense seed 13, 38 of 528 cars read over 6 m at the loops; 29 once it is not.)
LOW_END_M = 0.5
# A receding vehicle enters large at the image bottom: when it straddles two lanes (changing lanes) or its
# shadow or flank falls in the next lane, the features born there carry that lane's label and form a group
# of their own. A new group in a neighbouring lane of the same direction is such a side part when it moves
# with the vehicle, its near end is level with the vehicle's, and together they are no wider than one
# vehicle with its shadow. On the camera's side of the vehicle, where its raised parts do not lean, such a part is
# narrow across the road (its flank's lower edge, a shadow's edge along it); a car entering beside it shows its
# whole width there:
SIDE_SPEED_TOL = 0.1  # relative speed difference
SIDE_SPEED_TOL_WATCHED = 0.2  # ... of speeds averaged over SPEED_WINDOW_S, for a part watched RECHECK_VOTES frames
SIDE_DY_M = 2.0  # near ends this close along the road
SIDE_GAP_M = 1.0  # lateral gap between the two footprints
SIDE_NEAR_MAX_WIDTH_M = 1.0  # the part's near end no wider across the road, on the camera's side of the vehicle
SIDE_MAX_WIDTH_M = 3.5  # joint footprint width (two cars side by side span >= 5 m: lane 3.5 + car 1.7)
# ... or up to this with the image between the two one body (a tall vehicle's flank and top are projected wider:
# a 4 m high box from a 10 m pole spans 1.7 times its width; two cars side by side have road between them)
SIDE_MAX_WIDTH_TALL_M = 7.0
SIDE_TALL_HOST_M = 8.0  # ... of a vehicle this long in projection (a car beside a car in the next lane is shorter)
# ... and the group smaller than the vehicle when together they are as wide as two cars side by side (lane 3.5 m
# + car 1.7 m): a receding car entering beside another is as long in projection and as big as it
SIDE_PAIR_WIDTH_M = 5.2
# ... wider when the new group is only a shadow on the road (the image test says so): cast sideways by a
# low sun it reaches a lane or more across, starting a little behind or ahead of the vehicle
SHADOW_MAX_WIDTH_M = 9.0
# (the features seen on a long shadow lie on its far edge, 4-5 m from its caster's side; the image test then
# checks that the road between the two is shadowed too)
SHADOW_GAP_M = 6.0
# A group of fewer features than a vehicle needs may be a longer shadow's tip: a sun 12 degrees up casts a car's
# 7 m long, a van's 12 m, up to the far side of the lane beyond the next (SHADOW_LANES)
TIP_MAX_WIDTH_M = 12.5
TIP_GAP_M = 10.0
SHADOW_DY_M = 6.0
SHADOW_LANES = 2  # ... across the next lane into the one beyond
SHADOW_SPEED_TOL = 0.3  # a new group's features have not settled to its speed yet
SIDE_LATE_HOST_K = 2.0  # a flank reported before its vehicle joins it if the vehicle has this many times its features
# A group that the image test finds to be only a shadow on the road in most frames of its first watch
# (its caster may be lanes away under a low sun, or out of view) is no vehicle: it is retired unreported.
# It is judged before its first report is released (pipeline.HOLD_S), whatever the frame rate:
LONE_SHADOW_S = 0.25  # tested over this long ...
LONE_SHADOW_TESTS = 5  # ... and in at least this many frames ...
LONE_SHADOW_SHARE = 0.6  # ... of which this share must find a shadow
# A vehicle may show only a few features, in groups each too small to be reported (rain, dusk, a plain body):
# its roof and its bumper are further apart in projection than the connection distance when first seen far
# away. Settled features of two such groups of one lane link once they come within the connection distance,
# both moving, where the groups are alone: no group of the next lane moves beside them (within LATE_BESIDE_M
# along the road and LATE_BESIDE_X_M across, at LATE_BESIDE_K times their speed: a vehicle's flank, shadow or
# roof seen in the next lane), and no vehicle of their lane or the next could hold them as a part (within
# LATE_HOST_X_M of its footprint across the road, and from 2 m short of its near end to 2 m beyond
# ELEVATED_LENGTH_M or its own length along it, after undoing a height magnification of their speed ratio
# times 1 - LATE_HOST_K_SPREAD, 1 or 1 + LATE_HOST_K_SPREAD). A FAR pair stays FAR until it links or a feature
# is replaced: two lone small groups that close in on each other (motorcycles in a queue) may link, and only
# segmentation parts them again.
LATE_BESIDE_M = 15.0
LATE_BESIDE_X_M = 6.0
LATE_BESIDE_K = (0.7, 1.5)
LATE_HOST_X_M = 2.5
LATE_HOST_K_SPREAD = 0.15
# A tall vehicle's features at different heights move at different speeds in projection (its top's height
# magnification k over its bumper's), so their pairs' distances grow and segmentation parts them: with few features
# (rain, a plain body) it falls apart into groups each too small to be reported, and is never counted. Yet a point
# at height, its ground point D from the camera's foot, is seen k D away moving at k V: its distance over its speed
# is the time its ground point takes to reach the foot (since it passed it, receding), the same for every point of
# one vehicle's front (its bumper, windscreen and roof's front edge: ground places within V STACK_S of each other).
# Two such groups of a lane, on one side of the foot, settled and moving its way, the further one faster by a ratio
# of up to the largest magnification, within the connection distance of each other across the road, whose times to
# the foot agree within STACK_S, are one vehicle if so for STACK_HELD_S running with the image between them one body
# in every frame (the image test of joined parts): the further one joins the nearer one for good. At constant speeds
# a follower closing in on a vehicle of its lane so as to reach the foot with it moves just so, but the road is seen
# between the two. STACK_S is a quarter of the shortest time gap drivers keep (about 1 s; the synthetic scenes'
# queues 1.1-1.4 s), and no tighter: the time to the foot carries the speed's error, 5 % of 5 s far out. A reported
# vehicle across the road within LATE_BESIDE_X_M with about their time to the foot (from STACK_S less to
# ELEVATED_LENGTH_M over its speed more) may have them as its parts (a flank, a mirror and its shadow in the next
# lane): the rules for parts take them, not this one.
STACK_S = 0.25
STACK_HELD_S = 0.2
# An approaching vehicle's near end whose feature lay within EDGE_ROWS_K times the tracker's reach (its search
# radius and half a template) of the image's bottom and is gone has left the view there (the tracker drops a
# feature whose search window leaves the image): the near end goes on at the vehicle's speed from then on, as
# far as no lower feature shows it, rather than wait for the features further back. (Waiting made vehicles
# stand at the image's edge for a few frames, their time counted without distance: where a camera has
# drifted so far that its image ends inside the Edie region, speeds read 5-7 % low.)
EDGE_ROWS_K = 3.0
# A receding vehicle enters the view at the image's bottom, front first: until its rear is in view its lowest
# visible point stays in the bottom rows, ahead of its rear. A group not yet reported whose near end lies within
# ENTER_ROWS_K times the tracker's reach of the bottom starts its trajectory afresh (as after a standstill,
# STILL_S): counted from when its front came into view, its time in the Edie region ran 0.2 s long, and the
# receding lanes' speeds read 2-4 % low. Only while its front is short of its count line: where the line lies
# that close to the bottom (a vehicle entering over it counts where first seen), its first report must not wait.
# A group whose near end lay in its detection zone while it was begun afresh so has entered the view, wherever its
# trajectory begins (in a small frame the rows in reach run past the zone): taken for one found again mid-view, a
# vehicle reported with its front already over the line (its length measured only then) was never counted.
ENTER_ROWS_K = 2.0
# A feature younger than SETTLED_AGE moving its group's way at under this share of the median speed of the
# group's settled features (when that is MOVING_MPS or more) is not its near end: a corner on the road just
# uncovered behind a receding vehicle, whose first flow the vehicle's edge dragged along, is linked to it before
# its speed settles and would hold the near end back. (Settled features may be that slow: a truck's bumper
# under a low camera moves at half the speed of its box's top in projection.)
SLOW_REP_SHARE = 0.5
# A vehicle's id goes to the part of its group holding most features. Where an approaching vehicle's group comes
# apart into two parts of its own features moving at one speed (median speeds within FRONT_SPEED_TOL), the front
# one holding its near end and big enough to be reported, they are two vehicles joined for a while (a corner on
# the road between them, new and so not yet known to stand, linked both): the id, with its count and its near
# end, stays with the front (see Grouper._front_keeps_id). A raised part moves faster in projection, by its
# height's magnification (1.1-1.8), and is left to the rules for parts.
FRONT_SPEED_TOL = 0.05
# Two vehicles of an approaching lane reported over RECHECK_S ago (past the re-checks for parts) whose groups have
# run into one, the leader's near end KEEP_APART_M or more ahead of the follower's, both moving at about one speed
# (near ends' speeds within KEEP_APART_SPEED_TOL: the follower's may be a raised corner's, faster in projection),
# are two cars that features between them linked (a sign on the leader's roof, seen over the follower's bonnet):
# given the follower's id, the leader would vanish (uncounted if short of its line) and the follower be counted
# at the leader's time. Each keeps its own features (see Grouper._keep_apart), unless the follower, its height
# undone, lies on the leader (its raised part). (On a receding lane a raised part lies ahead of its vehicle.)
KEEP_APART_M = 7.0
KEEP_APART_SPEED_TOL = 0.2


@njit(cache=True)
def pair_update(live, s, lane, motion, state, rng, y0, conn_x, conn_y, seg_x, seg_y, seg_rel, late):
    """Update the pair graph over the live slots. Only features born in the same lane may link (side by
    side vehicles stay apart); a tall vehicle's top seen in the next lane is joined later as a fragment.
    Nor do a standing and a moving feature (motion STANDING and MOVING): a vehicle passing what stands
    still is not one object with it. A pair first seen further apart than the connection distance (FAR) links
    later if both slots may link late (late[slot], see LATE_BESIDE_M) and both move. rng[i, j] = (min dx,
    max dx, min dy, max dy) of the pair distance since linking; y0[i, j] = Y of the lower slot at linking (for
    the travelled distance)."""
    n = live.shape[0]
    for a in range(n):
        i = live[a]
        for b in range(a + 1, n):
            j = live[b]
            if i > j:
                i2, j2 = j, i
            else:
                i2, j2 = i, j
            dx = s[j2, 0] - s[i2, 0]
            dy = s[j2, 1] - s[i2, 1]
            st = state[i2, j2]
            if st == UNSEEN or st == FAR:
                near = abs(dx) < conn_x and abs(dy) < conn_y
                if st == FAR:
                    if near and late[i2] and late[j2] and motion[i2] == MOVING and motion[j2] == MOVING:
                        _link_pair(i2, j2, dx, dy, s, state, rng, y0)
                elif lane[i2] == lane[j2] and lane[i2] > 0 and motion[i2] * motion[j2] != STANDING * MOVING:
                    if near:
                        _link_pair(i2, j2, dx, dy, s, state, rng, y0)
                    else:
                        state[i2, j2] = FAR
                else:
                    state[i2, j2] = APART
            elif st == LINKED:
                r = rng[i2, j2]
                if dx < r[0]:
                    r[0] = dx
                if dx > r[1]:
                    r[1] = dx
                if dy < r[2]:
                    r[2] = dy
                if dy > r[3]:
                    r[3] = dy
                travel = abs(s[i2, 1] - y0[i2, j2])
                if r[1] - r[0] > seg_x or r[3] - r[2] > seg_y + seg_rel * travel:
                    state[i2, j2] = APART


@njit(cache=True)
def _link_pair(i, j, dx, dy, s, state, rng, y0):
    state[i, j] = LINKED
    rng[i, j, 0] = dx
    rng[i, j, 1] = dx
    rng[i, j, 2] = dy
    rng[i, j, 3] = dy
    y0[i, j] = s[i, 1]


@njit(cache=True)
def group_medians(members, starts, s, age):
    """Per group (members[starts[g]:starts[g + 1]]): the median X, Y and along-road speed of its features, and
    the age of its oldest."""
    ng = starts.shape[0] - 1
    out = np.empty((ng, 4))
    for g in range(ng):
        m = members[starts[g]:starts[g + 1]]
        out[g, 0] = _median_of(s[m, 0])
        out[g, 1] = _median_of(s[m, 1])
        out[g, 2] = _median_of(s[m, 3])
        out[g, 3] = age[m].max()
    return out


@njit(cache=True)
def _beside(l1, x1, y1, v1, l2, x2, y2, v2):
    """Whether a group (lane l2, place x2, y2, speed v2) of the next lane moves beside another (see
    LATE_BESIDE_M); v1 is not 0."""
    r = v2 / v1
    return (abs(l2 - l1) == 1 and abs(y2 - y1) <= LATE_BESIDE_M and abs(x2 - x1) <= LATE_BESIDE_X_M
            and LATE_BESIDE_K[0] <= r <= LATE_BESIDE_K[1])


@njit(cache=True)
def alone_groups(sl, sx, sy, sv, big, fx, fy, k_max):
    """Per small moving group (lane sl, median place sx, sy, speed sv, never 0): whether it is alone (see
    LATE_BESIDE_M): no other of these nor any vehicle group (rows of big: lane, x, near end, speed, x_lo, x_hi,
    the length it may reach along the road, whether it is big enough to be a vehicle) of the next lane moves
    beside it, and no vehicle of its lane or the next could hold it as a part, level or elevated (k_max 1:
    camera unknown)."""
    out = np.ones(sl.shape[0], np.bool_)
    for i in range(sl.shape[0]):
        for j in range(sl.shape[0]):
            if _beside(sl[i], sx[i], sy[i], sv[i], sl[j], sx[j], sy[j], sv[j]):
                out[i] = False
        for j in range(big.shape[0]):
            if not out[i]:
                break
            lj, vj = big[j, 0], big[j, 3]
            if _beside(sl[i], sx[i], sy[i], sv[i], lj, big[j, 1], big[j, 2], vj):
                out[i] = False
            if abs(lj - sl[i]) > 1 or sv[i] * vj <= 0 or big[j, 7] == 0:
                continue
            k0 = sv[i] / vj
            for spread in (1.0 - LATE_HOST_K_SPREAD, 1.0, 1.0 + LATE_HOST_K_SPREAD):
                k = min(max(spread * k0, 1.0), k_max)
                gx, gy = fx + (sx[i] - fx) / k, fy + (sy[i] - fy) / k
                if (big[j, 4] - LATE_HOST_X_M <= gx <= big[j, 5] + LATE_HOST_X_M
                        and big[j, 2] - 2.0 <= gy <= big[j, 2] + 2.0 + big[j, 6]):
                    out[i] = False
    return out


@njit(cache=True)
def unbridge(new, live, owner, s, state):
    """New features (age 0) link to at most one reported vehicle (owner[slot] its id, or -1): two vehicles
    following closely (a queue) would otherwise be joined for good by one feature between them. Each keeps
    its links to the vehicle it lies nearest to; returns that vehicle per new feature (or -1). Parts of one
    vehicle reported apart join it as fragments instead, which needs the camera's position (heights):
    without it the grouper does not call this."""
    kept = np.full(new.shape[0], -1)
    for a in range(new.shape[0]):
        i = new[a]
        best = -1
        best_d = np.inf
        several = False
        for j in live:
            if j == i or owner[j] < 0:
                continue
            st = state[i, j] if i < j else state[j, i]
            if st != LINKED:
                continue
            several = several or (best >= 0 and owner[j] != best)
            d = abs(s[j, 1] - s[i, 1]) + abs(s[j, 0] - s[i, 0])
            if d < best_d:
                best = owner[j]
                best_d = d
        kept[a] = best
        if several:
            _isolate(i, best, live, owner, state, True)
    return kept


@njit(cache=True)
def _isolate(i, keep, live, owner, state, owned_only):
    """Unlink feature i from every live feature not of vehicle keep (only from other vehicles' if
    owned_only)."""
    for j in live:
        if j == i or (keep >= 0 and owner[j] == keep) or (owned_only and owner[j] < 0):
            continue
        if i < j:
            if state[i, j] == LINKED:
                state[i, j] = APART
        elif state[j, i] == LINKED:
            state[j, i] = APART


@njit(cache=True)
def isolate(new, kept, live, owner, state):
    """New features that still join two vehicles through one another (or through a group of no vehicle)
    keep only their links to their own vehicle."""
    for a in range(new.shape[0]):
        _isolate(new[a], kept[a], live, owner, state, False)


@njit(cache=True)
def components(live, state, labels):
    """Vehicles over the live slots: the connected components of the LINKED graph, each with fragment
    features then joined to the one component it is most MERGED with as the fragment (never the other way
    round). A fragment joined to a vehicle for good so never holds together two parts of that vehicle that
    have since moved apart (two queued cars linked while crawling together, then the leader pulls away).
    labels[slot] = the smallest slot of its vehicle."""
    n = live.shape[0]
    parent = np.arange(n)
    merged = False
    for a in range(n):
        i = live[a]
        for b in range(a + 1, n):
            j = live[b]
            st = state[i, j] if i < j else state[j, i]
            if st == LINKED:
                _union(parent, a, b)
            elif st == MERGED_LO or st == MERGED_HI:
                merged = True
    for a in range(n):
        parent[a] = _root(parent, a)
    if merged:
        part = parent.copy()  # the LINKED components, by root
        shared = np.zeros((n, n), np.int32)  # [fragment's component, host's component] -> MERGED pairs
        for a in range(n):
            i = live[a]
            for b in range(a + 1, n):
                j = live[b]
                lo_a = i < j
                st = state[i, j] if lo_a else state[j, i]
                if (st == MERGED_LO or st == MERGED_HI) and part[a] != part[b]:
                    if (st == MERGED_LO) == lo_a:  # a's feature is the fragment's
                        shared[part[a], part[b]] += 1
                    else:
                        shared[part[b], part[a]] += 1
        for c in range(n):
            if part[c] == c:  # every component picks its host, also one that another has just joined
                host = np.argmax(shared[c])
                if shared[c, host] > 0:
                    _union(parent, c, host)
        for a in range(n):
            parent[a] = _root(parent, a)
    for a in range(n):
        labels[live[a]] = live[parent[a]]


@njit(cache=True)
def assign_ids(live, labels, fvid, next_vid, reported):
    """Vehicle ids for the components (labels) over the live slots, biggest component first (ties: lower
    label first): each takes the most frequent of its features' ids that no bigger one took (the lowest of
    equally frequent ones), the ids in ``reported`` (sorted) ranking before all others where it holds most of
    that id's live features, or a new one if none is left. Updates fvid; returns (order: the live slots
    grouped by component, biggest first; starts: each component's first index in order, then the end; vids:
    each component's id; next_vid)."""
    n = live.shape[0]
    order = np.empty(n, np.int64)
    starts = np.zeros(n + 1, np.int64)
    vids = np.empty(n, np.int64)
    if n == 0:
        return order, starts[:1], vids, next_vid
    lab = labels[live]
    srt = np.argsort(lab, kind="mergesort")
    held = np.sort(fvid[live])  # every id's live features, for the share a component holds of them
    ng = 1
    for a in range(1, n):
        if lab[srt[a]] != lab[srt[a - 1]]:
            ng += 1
    g0 = np.empty(ng + 1, np.int64)
    g = 0
    g0[0] = 0
    for a in range(1, n):
        if lab[srt[a]] != lab[srt[a - 1]]:
            g += 1
            g0[g] = a
    g0[ng] = n
    size = g0[1:] - g0[:-1]
    by_size = np.argsort(-size, kind="mergesort")
    pos = 0
    cand = np.empty(n, np.int64)
    for r in range(ng):
        c = by_size[r]
        starts[r] = pos
        m = 0
        for a in range(g0[c], g0[c + 1]):
            slot = live[srt[a]]
            order[pos] = slot
            pos += 1
            if fvid[slot] >= 0:
                cand[m] = fvid[slot]
                m += 1
        vid = -1
        if m:
            u = np.sort(cand[:m])
            best_n = 0
            a = 0
            while a < m:  # runs of equal ids, in increasing id order: the most frequent unclaimed one
                b = a
                while b < m and u[b] == u[a]:
                    b += 1
                # a reported id goes first (no count reaches n) where the component holds most of its features
                score = b - a
                j = np.searchsorted(reported, u[a])
                if j < reported.shape[0] and reported[j] == u[a]:
                    if 2 * score > np.searchsorted(held, u[a], "right") - np.searchsorted(held, u[a], "left"):
                        score += n
                if score > best_n:
                    taken = False
                    for q in range(r):
                        if vids[q] == u[a]:
                            taken = True
                            break
                    if not taken:
                        vid = u[a]
                        best_n = score
                a = b
        if vid < 0:
            vid = next_vid
            next_vid += 1
        vids[r] = vid
        for a in range(starts[r], pos):
            fvid[order[a]] = vid
    starts[ng] = pos
    return order, starts[:ng + 1], vids[:ng], next_vid


@njit(cache=True)
def fitted_places(members, fit, fit_vid, vid, k_max, frames, min_var):
    """Per member of group vid, from its straight-line fit against the group's near end (see fit_places): its
    place on the road behind the near end and the fit's slope (its height magnification, not clipped to
    [1, k_max] as the place's is); NaN for one not fitted (fewer than ``frames`` frames, or a near end whose
    distance varied less than ``min_var`` over them)."""
    places = np.full(members.shape[0], np.nan)
    slopes = np.full(members.shape[0], np.nan)
    for a in range(members.shape[0]):
        i = members[a]
        n = fit[i, 0]
        if fit_vid[i] != vid or n < frames:
            continue
        var = fit[i, 3] / n - (fit[i, 1] / n) ** 2
        if var < min_var:
            continue
        slopes[a] = (fit[i, 4] / n - fit[i, 1] * fit[i, 2] / (n * n)) / var
        places[a] = fit[i, 2] / n / min(max(slopes[a], 1.0), k_max) - fit[i, 1] / n
    return places, slopes


@njit(cache=True)
def fit_places(members, age, s, fit, fit_vid, vid, d, cy, k_max, frames, min_var, neighbour):
    """Add this frame to the straight-line fits (see Grouper._ground_length) of a group's settled features
    against its near end, d from the camera's foot along the road (a fit made for another group starts
    afresh). Returns how far behind the near end the group's far end lies on the road, and its height
    magnification: the furthest fitted feature with another within ``neighbour``, else their median (of an even
    count, the middle two's means); (NaN, NaN) while none is fitted, or while one not yet fitted lies further
    (a fragment that just joined)."""
    for a in range(members.shape[0]):
        i = members[a]
        if age[i] < 3:
            continue
        if fit_vid[i] != vid:
            for c in range(5):
                fit[i, c] = 0.0
            fit_vid[i] = vid
        q = s[i, 1] - cy
        fit[i, 0] += 1.0
        fit[i, 1] += d
        fit[i, 2] += q
        fit[i, 3] += d * d
        fit[i, 4] += d * q
    fitted, slopes = fitted_places(members, fit, fit_vid, vid, k_max, frames, min_var)
    places = np.empty(members.shape[0])
    ks = np.empty(members.shape[0])
    n_ok = 0
    q_ok = -np.inf
    q_new = -np.inf
    for a in range(members.shape[0]):
        if age[members[a]] < 3:
            continue
        q = s[members[a], 1] - cy
        if np.isnan(fitted[a]):
            q_new = max(q_new, q)
        else:
            places[n_ok] = fitted[a]
            ks[n_ok] = min(max(slopes[a], 1.0), k_max)
            n_ok += 1
            q_ok = max(q_ok, q)
    if n_ok == 0 or q_new > q_ok:
        return np.nan, np.nan
    order = np.argsort(places[:n_ok], kind="mergesort")
    p = places[:n_ok][order]
    pk = ks[:n_ok][order]
    for a in range(n_ok - 1, 0, -1):
        if p[a] - p[a - 1] <= neighbour:
            return p[a], pk[a]
    h = n_ok // 2
    if n_ok % 2:
        return p[h], pk[h]
    return (p[h - 1] + p[h]) / 2.0, (pk[h - 1] + pk[h]) / 2.0


@njit(cache=True)
def _median_of(a):
    """np.median's value for the few numbers of one group, without its overhead."""
    a = np.sort(a)
    n = a.shape[0]
    return a[n // 2] if n % 2 else (a[n // 2 - 1] + a[n // 2]) / 2.0


@njit(cache=True)
def group_summary(members, s, px, age, near_m, spot_m, moving, standing, fast, fast_min):
    """One group's moving body and near end: its features without those standing still (below ``standing``
    while their median moves above ``moving``: road texture just uncovered beside a vehicle, linked before its
    speed showed, is not on it), its lowest feature in the image (nearest the camera: the near end) other than
    a settled one faster in projection than ``fast`` times the median speed of the body's settled features when
    there are 4 or more and their median is ``fast_min`` or more (see REP_FAST_K), and the low part within
    ``near_m`` of it along the road, which gives the velocity (its settled features) and the place and footprint
    across the road; the settled features within ``spot_m`` give the spot speed (else it is vy). Returns (body,
    near end's slot, body's span along the road, vx, vy, spot vy, x, x_lo, x_hi)."""
    v = np.abs(s[members, 3])
    body = members
    if _median_of(v) > moving:
        keep = v >= standing
        if keep.any():
            body = members[keep]
    settled = body[age[body] >= 3]
    v_max = fast * _median_of(np.abs(s[settled, 3])) if settled.shape[0] >= 4 else np.inf
    if v_max < fast * fast_min:
        v_max = np.inf
    v_med = _median_of(s[settled, 3]) if settled.shape[0] >= 2 else 0.0
    v_slow = SLOW_REP_SHARE * abs(v_med) if abs(v_med) >= moving else -np.inf
    rep = rep_any = -1  # rep_any: the lowest not too fast, for a group whose every one is too fast or too slow
    y_lo = y_hi = s[body[0], 1]
    for i in body:
        if not (age[i] >= 3 and abs(s[i, 3]) > v_max):
            if rep_any < 0 or px[i, 1] > px[rep_any, 1]:
                rep_any = i
            if (rep < 0 or px[i, 1] > px[rep, 1]) and not (age[i] < SETTLED_AGE and s[i, 3] * np.sign(v_med) < v_slow):
                rep = i
        y_lo = min(y_lo, s[i, 1])
        y_hi = max(y_hi, s[i, 1])
    if rep < 0:
        rep = rep_any
    low = np.empty(body.shape[0], np.int64)
    near = np.empty(body.shape[0], np.int64)
    spot = np.empty(body.shape[0], np.int64)
    n_low = n_near = n_spot = 0
    for i in body:
        if abs(s[i, 1] - s[rep, 1]) < near_m:
            low[n_low] = i
            n_low += 1
            if age[i] >= 3:
                near[n_near] = i
                n_near += 1
                if abs(s[i, 1] - s[rep, 1]) < spot_m:
                    spot[n_spot] = i
                    n_spot += 1
    vx, vy = s[rep, 2], s[rep, 3]
    if n_near:
        vx, vy = _median_of(s[near[:n_near], 2]), _median_of(s[near[:n_near], 3])
    vs = _median_of(s[spot[:n_spot], 3]) if n_spot else vy
    xs = s[low[:n_low], 0]
    return body, rep, y_hi - y_lo, vx, vy, vs, _median_of(xs), xs.min(), xs.max()


@njit(cache=True)
def _root(parent, a):
    while parent[a] != a:
        a = parent[a]
    return a


@njit(cache=True)
def _union(parent, a, b):
    ra, rb = _root(parent, a), _root(parent, b)
    if ra < rb:
        parent[rb] = ra
    elif rb < ra:
        parent[ra] = rb


def motion_class(s: np.ndarray, age: np.ndarray) -> np.ndarray:
    """Per feature slot: STANDING, MOVING or 0 (see pair_update)."""
    v = np.abs(s[:, 3])
    m = np.zeros(len(s), np.int8)
    m[(v < STANDING_MPS) & (age >= SETTLED_AGE)] = STANDING
    m[v > MOVING_MPS] = MOVING
    return m


def _elevated_reach(lo: float, hi: float) -> float:
    """How far along the road an elevated part of a vehicle with footprint [lo, hi] may lie: as far as the
    longest vehicle reaches, with a metre's slack at each end."""
    return max(hi, lo + 1.0 + ELEVATED_LENGTH_M + 1.0)


def _elevated_x(x_lo: float, x_hi: float) -> tuple[float, float]:
    """Across the road, where an elevated part of a vehicle with footprint [x_lo, x_hi] may lie (its height
    undone): that footprint, widened to ELEVATED_WIDTH_M."""
    return min(x_lo, x_hi - ELEVATED_WIDTH_M), max(x_hi, x_lo + ELEVATED_WIDTH_M)


def _elevated_on(gx: float, gy: float, lo: float, hi: float, x_lo: float, x_hi: float, margin: float) -> bool:
    """Whether an elevated part whose height is undone to road point (gx, gy) lies on a vehicle with footprint
    [lo, hi] along the road and [x_lo, x_hi] across: across, over its body's width (_elevated_x) with a margin;
    along, from its footprint's start as far as the longest vehicle reaches (_elevated_reach)."""
    x_lo, x_hi = _elevated_x(x_lo, x_hi)
    return lo <= gy <= _elevated_reach(lo, hi) and x_lo - margin <= gx <= x_hi + margin


def _extent(o: VehicleState, length: float | None = None) -> tuple[float, float]:
    """Along-road span a vehicle surely covers: its features' span (or its own length without joined
    fragments), at least MIN_LENGTH_M, from its near end (the end nearer the camera, lower Y: the front of an
    approaching vehicle, the rear of a receding one; the far end is a roofline projected beyond the vehicle),
    plus a metre of slack each way."""
    near = min(o.y_front, o.y_rear)
    span = abs(o.y_front - o.y_rear) if length is None else length
    return near - 1.0, near + max(span, MIN_LENGTH_M) + 1.0


def _take_state(out: list[VehicleState], vid: int) -> VehicleState | None:
    """Remove vehicle vid's state from this frame's states (in place) and return it; None if it has none."""
    for i, st in enumerate(out):
        if st.id == vid:
            return out.pop(i)
    return None


class Lost(NamedTuple):
    """A reported vehicle whose features were all lost inside its detection zone (it may be found again)."""

    t: float
    lane_index: int
    near: float  # its near end then
    speed: float  # m/s
    x: float = float("nan")  # across the road
    front: float = float("nan")  # its front along the road
    brief: bool = False  # lost within LOST_MIN_REPORTED_S of its report


@dataclass
class VehicleTrack:
    """Bookkeeping of one vehicle hypothesis across frames."""

    id: int
    first_t: float
    lane_index: int
    frames: int = 0
    n_max: int = 0
    reported: bool = False
    start_y: float = 0.0
    x_lo: float = 0.0
    x_hi: float = 0.0
    last: VehicleState | None = None
    report_t: float = 0.0
    n_now: int = 0
    own_length: float = 0.0  # the group's length before fragments joined it
    merged: bool = False
    votes: tuple[int, int, float] = (0, 0, 0.0)  # (candidate host, frames it matched, place on it)
    vote_t: float = -np.inf  # when it last matched the candidate host
    watch_host: int = 0  # a vehicle this new group may be an elevated part of (see Grouper._watched) ...
    watch: list[tuple[float, float, bool]] = field(default_factory=list)  # ... (t, speed ratio, matched it)
    unsure: bool = False  # watched on its first speeds alone (see Grouper._unsure_host)
    shadow_tests: tuple[float, int, int] | None = None  # (first test's time, frames tested, frames found
    # only a shadow on the road)
    ground: tuple[float, float, int] | None = None  # reported length, far end on the road, lane direction
    fitted: bool = False  # the length has been measured from fitted features (see Grouper._ground_length)
    still_y: float = float("nan")  # where the near end has stood (within STILL_M) ...
    still_t: float = 0.0  # ... since when
    fast_t: float = float("-inf")  # when it last moved at MOVING_MPS or faster
    # the near end's speed over SPEED_WINDOW_S (or None), for the trajectory's (last t, length) it was taken on
    _near_vy: tuple[tuple[float | None, int], float | None] = ((None, 0), None)
    trajectory: list[tuple[float, float, float]] = field(default_factory=list)
    path: list[tuple[float, float, float]] = field(default_factory=list)  # a small group's (t, X, Y) medians
    adopted: float = 0.0  # the furthest place behind the near end of a part it adopted (see ADOPT_K_MIN)
    near_slot: int = -1  # the near end's feature in the last frame ...
    near_row: float = 0.0  # ... its image row then
    leaving: bool = False  # its near end has left the image at its bottom (see EDGE_ROWS_K)
    entered_at_bottom: bool = False  # its near end was in its detection zone as it entered (see ENTER_ROWS_K)

    def elevated_x(self) -> tuple[float, float]:
        """Across the road, where an elevated part of it may lie (its height undone): its footprint, widened to
        ELEVATED_WIDTH_M."""
        return _elevated_x(self.x_lo, self.x_hi)

    def carries(self, gx: float, gy: float, margin: float = FRAGMENT_X_MARGIN_M) -> bool:
        """Whether an elevated part whose height is undone to road point (gx, gy) lies on this vehicle (see
        _elevated_on)."""
        lo, hi = _extent(self.last, self.own_length)
        return _elevated_on(gx, gy, lo, hi, self.x_lo, self.x_hi, margin)

    def steady_vy(self, fallback: float) -> float:
        """The along-road speed of the near end over the last SPEED_WINDOW_S (steadier than one frame's), or
        the features' speed (fallback) if that is faster: a near end lags its features while it is held at
        the image's edge (a receding vehicle entering at the bottom) or while its lowest feature changes.
        It is the median of its steps' rates: a near end that jumps (a lower feature joined, such as the
        corner of the vehicle's shadow) moves so in one step, which would add metres to the run over the window."""
        tr = self.trajectory
        if len(tr) < 3:
            return fallback
        t1 = tr[-1][0]
        if self._near_vy[0] == (t1, len(tr)):
            v = self._near_vy[1]
        else:
            i = len(tr) - 1
            while i > 0 and t1 - tr[i][0] < SPEED_WINDOW_S:
                i -= 1
            pts = np.array([(p[0], p[2]) for p in tr[i:]])
            dt = np.diff(pts[:, 0])
            ok = dt > 0.0
            v = float(np.median(np.diff(pts[:, 1])[ok] / dt[ok])) if t1 - pts[0, 0] >= 0.2 and ok.any() else None
            self._near_vy = ((t1, len(tr)), v)
        return fallback if v is None or abs(fallback) > abs(v) else v


class Grouper:
    """Turns tracked features into provisional and finalised vehicles, one ``step`` per frame."""

    def __init__(self, params: TrackingParams, zones: SiteZones) -> None:
        n = params.max_features
        self.p = params
        self.zones = zones
        self.state = np.zeros((n, n), np.int8)
        self.rng = np.zeros((n, n, 4), np.float32)
        self.y0 = np.zeros((n, n), np.float32)
        self.late = np.zeros(n, np.bool_)  # per slot: may link late (see LATE_BESIDE_M), as of the last step
        self.stacked: dict[tuple[int, int], float] = {}  # small groups' pairs seen as one vehicle: since when
        self.labels = np.full(n, -1, np.int64)
        self.fvid = np.full(n, -1, np.int64)
        # per feature, its straight-line fit against its group's near end (see _ground_length): frames, and
        # the sums of d (the near end's distance from the camera's foot), q (its own), d * d and d * q
        self.fit = np.zeros((n, 5), np.float64)
        self.fit_vid = np.full(n, -1, np.int64)  # the group that fit is for
        self.cut_off = np.full(n, -1, np.int64)  # per slot: the vehicle it was cut off (see LONGEST_M), or -1
        # per slot: a feature of a shadow joined to its vehicle (see _side_host), which keeps it from being
        # found as a vehicle again but is no part of its place on the road
        self.shade = np.zeros(n, np.bool_)
        # per slot: found off the lanes, where only vehicles' tops are seen (see SiteZones._lifted): an elevated
        # part of a vehicle, or nothing on the road; they do not count among a group's features (n_now, n_max)
        self.lifted = np.zeros(n, np.bool_)
        self.tracks: dict[int, VehicleTrack] = {}
        self.next_vid = 1
        self.steps = 0
        self.settled_t = np.inf  # the time of step START_SETTLE_STEPS
        self.finished_total = 0
        self._place = 0.0
        self._k = 1.0  # the speed ratio of the last group _host_of matched to its host (1 for a side part)
        self._by_shadow = False  # ... and whether it matched as the host's shadow
        self._ghost_of: int | None = None  # the vehicle that left the view whose top it found (see GHOST_S)
        self.lights_only = False  # a night scene: vehicles seen by their lights alone (set by the pipeline)
        self.merged_now: set[int] = set()  # groups joined to another vehicle in the last step (for the pipeline's hold)
        # finished vehicles' last states (exited as they finished), footprints across and lanes, for their leftovers
        self.recent: list[tuple[VehicleState, float, float, int]] = []
        self.lost: list[Lost] = []  # reported vehicles lost
        self.foot = zones.camera  # (X, Y, height) of the camera, or None
        self.edge_rows = EDGE_ROWS_K * (params.search_radius_px + params.template_px // 2)
        self.k_max = zones.k_max
        self.length_foot, self.length_k_max = zones.length_camera, zones.length_k_max  # see _ground_length
        self.length_k_level = zones.length_magnification(LOW_END_M) or 1.0  # see LOW_END_M
        self.k_top = zones.magnification(LIFTED_TOP_M) or self.k_max  # see LIFTED_TOP_M
        self.k_far = zones.magnification(ADOPT_FAR_MIN_HEIGHT_M) or np.inf  # see ADOPT_FAR_M

    @property
    def min_report(self) -> int:
        """The features a group needs to be reported (at night one fewer: SMALL_S)."""
        return self.p.min_features - int(self.lights_only)

    def reset_slots(self, slots: np.ndarray, lifted: np.ndarray | None = None) -> None:
        """Forget every pair involving slots that now hold new features (lifted: which were found off the lanes)."""
        self.state[slots, :] = UNSEEN
        self.state[:, slots] = UNSEEN
        self.fvid[slots] = -1
        self.fit_vid[slots] = -1
        self.cut_off[slots] = -1
        self.late[slots] = False
        self.shade[slots] = False
        self.lifted[slots] = False if lifted is None else lifted

    def _components(self, t: float, live: np.ndarray, s: np.ndarray, age: np.ndarray, reported: np.ndarray
                    ) -> None:
        """Label the connected components of the pair graph (self.labels). With the camera known, no feature
        found this frame (age 0: born, or never matched since) joins two reported vehicles (``reported``: their
        ids, sorted; see unbridge), nor a vehicle and a part cut off it (see LONGEST_M):
        parts of one vehicle reported apart then join it as fragments, by their height. That holds for a
        vehicle with few features left too (a queued car whose other features were lost: joined, its count
        would go), unless it may still turn out to be a part of another vehicle of its lane: small, reported
        within RECHECK_S, and matched by a re-check (at least once) to a host still there in its lane (a tall
        vehicle's top, which a new feature between the two may then join to it; a side part or a shadow, whose
        host is in the next lane, no new feature could join to its host), or moves as an elevated part of a
        bigger one (see PART_MIN_MPS)."""
        if self.foot is None:
            components(live, self.state, self.labels)
            return
        parts = self._elevated_parts(reported)
        ids = [vid for vid in reported if not self._on_trial(self.tracks[vid], t) and vid not in parts]
        owner = np.where(np.isin(self.fvid, ids), self.fvid, -1)
        owner = np.where((owner < 0) & (self.cut_off >= 0), CUT_OWNER + self.cut_off, owner)
        new = live[age[live] == 0]
        kept = unbridge(new, live, owner, s, self.state) if len(new) else None
        components(live, self.state, self.labels)
        if kept is None or len(np.unique(kept[kept >= 0])) < 2:  # two vehicles are joined through two of them
            return
        owner_live = owner[live]
        own = owner_live >= 0
        pairs = np.unique(np.stack([self.labels[live][own], owner_live[own]]), axis=1)
        labels, n = np.unique(pairs[0], return_counts=True)
        joint = np.isin(self.labels[new], labels[n > 1])
        if joint.any():
            isolate(new[joint], kept[joint], live, owner, self.state)
            components(live, self.state, self.labels)

    def _elevated_parts(self, ids: np.ndarray) -> set[int]:
        """Reported vehicles (of ids) that move as an elevated part of a bigger reported one of their lane or the
        next (see PART_MIN_MPS): faster in projection by a height's magnification k, their near end (k undone)
        on its footprint; as of the last step."""
        cur = [tr for tr in (self.tracks[v] for v in ids) if tr.last is not None and tr.trajectory]
        if len(cur) < 2:
            return set()
        lane, n = (np.array([[tr.lane_index, tr.n_now] for tr in cur]).T)
        y, x, vy, x_lo, x_hi = np.array([[tr.trajectory[-1][2], tr.last.x, tr.last.vy, tr.x_lo, tr.x_hi]
                                         for tr in cur]).T
        lo, hi = np.array([_extent(tr.last, tr.own_length) for tr in cur]).T
        fy = self.foot[1]
        with np.errstate(divide="ignore", invalid="ignore"):
            k = vy[:, None] / vy[None, :]  # [part, vehicle]
        ok = ((n[None, :] > n[:, None]) & (np.abs(lane[:, None] - lane[None, :]) <= 1)
              & (k >= RECHECK_K_MIN) & (k <= self.k_max) & (np.abs(vy)[None, :] >= PART_MIN_MPS))
        k = np.where(ok, k, 1.0)
        gx, gy = self._on_road(x[:, None], y[:, None], k)
        slack = (1.0 - 1.0 / k) * FOOT_UNCERTAINTY * np.abs(y[:, None] - fy)
        on = (ok & (gy >= lo[None, :] - slack) & (gy <= hi[None, :] + slack)
              & (gx >= x_lo[None, :] - FRAGMENT_X_MARGIN_M) & (gx <= x_hi[None, :] + FRAGMENT_X_MARGIN_M))
        return {cur[i].id for i in np.flatnonzero(on.any(axis=1))}

    def _on_trial(self, tr: VehicleTrack, t: float) -> bool:
        """Whether a reported group may still be a part of another vehicle of its lane (see _components)."""
        host = self.tracks.get(tr.votes[0]) if tr.votes[1] else None
        return (tr.n_now < self.p.min_features and t - tr.report_t <= RECHECK_S and host is not None
                and host.lane_index == tr.lane_index)

    def _assign_ids(self, live: np.ndarray, reported: np.ndarray) -> dict[int, np.ndarray]:
        """Each component's vehicle id. A reported vehicle's id goes before a group's not yet reported (that
        one is provisional) in the component holding most of its features: a crawling car left with few corners
        that links up with a small group found on it, or on the car behind, stays that car, its count and its
        time in the region going on; a single corner of it in a bigger group does not take its id away. (Step then
        hands an approaching vehicle that came apart at one speed back its front, _front_keeps_id, and one that ran
        into the vehicle behind it its features, _keep_apart.)"""
        order, starts, vids, self.next_vid = assign_ids(live, self.labels, self.fvid, self.next_vid, reported)
        return {int(v): order[a:b] for v, a, b in zip(vids, starts[:-1], starts[1:])}

    def _approaching(self, tr: VehicleTrack) -> bool:
        """Whether a vehicle is in a lane whose traffic approaches the camera."""
        return tr.lane_index > 0 and self.zones.sign_by_index[tr.lane_index] < 0

    def _front_keeps_id(self, groups: dict[int, np.ndarray], before: np.ndarray, s: np.ndarray,
                        age: np.ndarray) -> None:
        """After _assign_ids (before: the ids it started from): a reported approaching vehicle whose near end's
        feature is now in a new group of mostly its own features, big enough to be reported and moving at its
        rest's speed (see FRONT_SPEED_TOL), takes that group back; the rest gets the new id."""
        touched: set[int] = set()
        for vid in groups:  # only existing keys' values change below
            tr = self.tracks.get(vid)
            if tr is None or not tr.reported or not self._approaching(tr):
                continue
            f = tr.near_slot
            if f < 0 or age[f] == 0 or before[f] != vid or self.fvid[f] == vid:
                continue  # its near end's feature is gone, or still its own
            other = int(self.fvid[f])
            if other in self.tracks or other in touched:
                continue  # another group's id (the rest would take over its history), or one given out already
            front, rest = groups[other], groups[vid]
            front_own, rest_own = (m[~(self.shade[m] | self.lifted[m])] for m in (front, rest))
            if len(front_own) < self.min_report or not len(rest_own) \
                    or 2 * np.count_nonzero(before[front] == vid) <= len(front):
                continue  # too small to be a vehicle, or mostly another group's
            v_front, v_rest = (float(np.median(np.abs(s[m, 3]))) for m in (front_own, rest_own))
            if min(v_front, v_rest) < MOVING_MPS or abs(v_front / v_rest - 1.0) > FRONT_SPEED_TOL:
                continue
            self.fvid[rest], self.fvid[front] = other, vid
            groups[vid], groups[other] = front, rest
            touched.update((vid, other))

    def _keep_apart(self, t: float, groups: dict[int, np.ndarray], before: np.ndarray, s: np.ndarray,
                    reported: np.ndarray) -> None:
        """After _assign_ids and _front_keeps_id (before: the ids they started from; reported: the reported
        vehicles' ids): an established vehicle of an approaching lane whose id vanished into the group of one
        KEEP_APART_M or more behind it takes its features back (see KEEP_APART_M), with the group's features of no
        reported vehicle that lie nearer its own along the road. (The pair graph links the two again next frame;
        this parts them again.)"""
        for vid in reported.tolist():
            tr = self.tracks[vid]
            if vid in groups or not self._approaching(tr) or tr.last is None or not tr.trajectory:
                continue
            own = np.flatnonzero(before == vid)
            own = own[self.fvid[own] != vid]  # its features alive now (the dead keep its id)
            if not len(own):
                continue
            ids, counts = np.unique(self.fvid[own], return_counts=True)
            w = int(ids[np.argmax(counts)])
            o = self.tracks.get(w)
            if w < 0 or o is None or w not in groups or not o.reported or o.last is None or not o.trajectory:
                continue
            if o.lane_index != tr.lane_index or min(t - tr.report_t, t - o.report_t) <= RECHECK_S:
                continue
            va, vb = abs(tr.steady_vy(tr.last.vy)), abs(o.steady_vy(o.last.vy))
            if min(va, vb) < MOVING_MPS or abs(va / vb - 1.0) > KEEP_APART_SPEED_TOL:
                continue
            ya, yb = tr.trajectory[-1][2], o.trajectory[-1][2]
            if ya > yb - KEEP_APART_M:
                continue  # not the one ahead (nearer the camera), or not by a vehicle's length
            if vb / va > LEVEL_K and self.foot is not None and tr.carries(*self._on_road(o.last.x, yb, vb / va)):
                continue
            m = groups[w]
            mine = before[m] == vid
            if np.count_nonzero(mine) < self.min_report:
                continue
            theirs = before[m] == w
            new = ~(mine | theirs | np.isin(before[m], reported))
            if new.any() and theirs.any():
                y = s[m, 1]
                da = np.abs(y[new][:, None] - y[mine][None, :]).min(axis=1)
                db = np.abs(y[new][:, None] - y[theirs][None, :]).min(axis=1)
                mine[np.flatnonzero(new)[da < db]] = True
            if mine.all():
                continue
            groups[vid], groups[w] = m[mine], m[~mine]
            self.fvid[m[mine]] = vid

    def step(self, t: float, s: np.ndarray, px: np.ndarray, lane: np.ndarray, alive: np.ndarray, age: np.ndarray,
             is_shadow: Callable[[np.ndarray, np.ndarray | None], bool] | None = None,
             is_joined: Callable[..., bool] | None = None,
             ) -> tuple[list[VehicleState], np.ndarray]:
        """Returns the vehicle states for this frame and the feature slots to retire (finalised vehicles).
        is_shadow(points, caster points) tells whether image points lie on a shadow of the caster's (with
        caster None: on a shadow at all); is_joined(points, other points[, share]) whether the image between the
        two is one body, not the road (in that share of it, or the image test's own)."""
        p = self.p
        self.steps += 1
        if self.steps == START_SETTLE_STEPS:
            self.settled_t = t
        live = np.flatnonzero(alive)
        retire: list[np.ndarray] = []
        out: list[VehicleState] = []
        groups: dict[int, np.ndarray] = {}
        ground: dict[int, tuple[float, float, int] | None] = {}
        pending: list = []
        small: list[tuple[int, np.ndarray]] = []  # groups of a lane too small to be reported: (id, members)
        self.merged_now = set()
        if len(live):
            # features found off the lanes link only among themselves: vehicles' tops, joined to a vehicle only
            # as an adopted part (see ADOPT_K_MIN)
            pair_update(live, s, np.where(self.lifted, lane + LIFTED_LANES, lane), motion_class(s, age), self.state,
                        self.rng, self.y0, p.connection_lateral_m, p.connection_m, p.segmentation_lateral_m,
                        p.segmentation_m, p.segmentation_per_m, self.late)
            reported = np.array(sorted(vid for vid, tr in self.tracks.items() if tr.reported), dtype=np.int64)
            self._components(t, live, s, age, reported)
            before = self.fvid.copy()
            groups = self._assign_ids(live, reported)
            self._front_keeps_id(groups, before, s, age)
            self._keep_apart(t, groups, before, s, reported)

        def seen(host: int) -> np.ndarray:
            """A host's slots but its tops seen off the lanes (they lie over whatever follows it in the image)."""
            m = groups[host]
            return m[~self.lifted[m]]

        def on_shadow(a: np.ndarray, host: int) -> bool:
            """The image test for a group (slots) lying only on the host's shadow, or whose near end does while
            the rest of it is the host's raised parts (a van's windscreen found with the corner of its shadow)."""
            caster = px[seen(host)] if host in groups else px[:0]
            if len(caster) == 0:
                return False
            if is_shadow(px[a], caster):
                return True
            near = s[a, 1] < s[a, 1].min() + NEAR_REP_M
            return not near.all() and self._raised_over(a[~near], host, s) and is_shadow(px[a[near]], caster)

        shadow = None if is_shadow is None else on_shadow
        # joined(group slots, host id): the image test for a group and the host being one body
        joined = None if is_joined is None else (
            lambda a, host, share=None: host in groups and len(seen(host)) > 0
            and is_joined(px[a], px[seen(host)], share))
        for vid in list(self.tracks):
            if vid not in groups:
                self._lose(self.tracks.pop(vid), t, out)
        self.recent = [r for r in self.recent if t - r[0].t <= GHOST_S]
        for vid, members in groups.items():
            lanes = lane[members]
            tr = self.tracks.get(vid)
            if tr is None:
                li = int(np.bincount(lanes).argmax())
                tr = VehicleTrack(id=vid, first_t=t, lane_index=li)
                self.tracks[vid] = tr
            tr.frames += 1
            tr.n_now = len(members) - int(np.count_nonzero(self.lifted[members]))  # its tops off the lanes aside
            tr.n_max = max(tr.n_max, tr.n_now)
            if not tr.reported and tr.n_max < self.min_report:
                if not tr.trajectory:  # too small to be a vehicle yet: only remember where it started
                    tr.trajectory.append((t, float(s[members[0], 0]), float(s[members[0], 1])))
                    tr.start_y = tr.trajectory[0][2]
                if tr.lane_index > 0:
                    small.append((vid, members))
                continue
            own = members[~(self.shade[members] | self.lifted[members])]
            body, rep, length, vx, vy, spot, x, tr.x_lo, tr.x_hi = group_summary(
                own if len(own) else members, s, px, age, NEAR_REP_M, SPOT_M, MOVING_MPS, STANDING_MPS, REP_FAST_K,
                REP_FAST_MIN_MPS)
            lz = self.zones.by_index(tr.lane_index) if tr.lane_index > 0 else None
            sign = lz.sign if lz is not None else -1
            rep_y = float(s[rep, 1])
            # The representative point is the near end: the front of an approaching vehicle, the rear of a
            # receding one. It never goes backwards: when the lowest feature is lost and the next one is further
            # back, the near end waits for it. (Carrying it on at the vehicle's speed instead made it creep
            # ahead of the vehicle: every change of lowest feature, between features at about the same place,
            # added a lead, and the features' speed is above the road's for any feature above the road.)
            if tr.trajectory:
                prev = tr.trajectory[-1][2]
                if sign < 0 and rep_y > prev and (tr.leaving or (
                        tr.near_slot not in members and tr.near_row >= self.zones.height - self.edge_rows)):
                    tr.leaving = True  # see EDGE_ROWS_K
                    rep_y = prev + vy * (t - tr.trajectory[-1][0])
                rep_y = min(prev, rep_y) if sign < 0 else max(prev, rep_y)
            else:
                tr.start_y = rep_y
            tr.near_slot, tr.near_row = int(rep), float(px[rep, 1])
            g = self._ground_length(tr, sign, body, s, age, rep_y, length)
            if tr.reported and sign < 0 and g > LONGEST_M:
                cut = self._split_off(tr, members, s)
                if cut is not None:  # the part behind is a group of its own from the next frame
                    members, g = members[cut[0]], min(g, cut[1])
                    groups[vid] = members
            if sign < 0:
                front, rear = rep_y, rep_y + length
                tr.ground = (g, rep_y + g, sign)
            else:  # the front of a receding vehicle is its far end: keep it monotone too
                front = rep_y + length if tr.last is None else max(rep_y + length, tr.last.y_front)
                rear = rep_y
                tr.ground = (g, max(rep_y + g, tr.ground[1]) if tr.ground else rep_y + g, sign)
            ground[vid] = tr.ground
            st = VehicleState(
                id=vid, t=t, x=x, y_front=front, y_rear=rear, vx=vx,
                vy=vy, length=length, n_features=int(len(members)), spot_vy=float(spot),
            )
            if abs(vy) >= MOVING_MPS:
                tr.fast_t = t
            elif (tr.reported and abs(vy) <= STANDING_MPS and float(np.abs(s[members, 3]).max()) < MOVING_MPS
                  and (t - tr.fast_t <= DEAD_STOP_S or _near_end_stopped_dead(tr, t))):
                self.tracks.pop(vid)  # stopped dead: the vehicle is lost where it last moved
                retire.append(members)
                self._lose(tr, t, out)
                continue
            tr.last = st
            if is_shadow is not None and self._lone_shadow(tr, t, px[members], is_shadow):
                self._retire_as_part(tr, st, NO_VEHICLE, members, retire, out)
                continue
            if not tr.merged:
                tr.own_length = length
            tr.trajectory.append((t, st.x, rep_y))
            if not abs(rep_y - tr.still_y) <= STILL_M:
                tr.still_y, tr.still_t = rep_y, t
            entering = (not tr.reported and sign > 0 and rep_y + tr.ground[0] < lz.count_y
                        and tr.near_row >= self.zones.height - ENTER_ROWS_K * self.edge_rows)
            if entering:
                tr.entered_at_bottom = tr.entered_at_bottom or lz.in_detection(tr.trajectory[0][2])
            if entering or (not tr.reported and t - tr.still_t >= STILL_S):
                tr.trajectory = tr.trajectory[-1:]
                tr.start_y = rep_y
            moved = abs(rep_y - tr.start_y) >= MIN_TRAVEL_M and abs(vy) >= MIN_SPEED_MPS
            if lz is not None and lz.in_exit(rep_y if tr.leaving else float(s[rep, 1])):
                self.tracks.pop(vid)
                retire.append(members)
                if self._orphaned_part(tr, t):
                    self._end_as_part(tr, st, tr.votes[0], out)
                elif tr.reported:
                    out.append(self._finish(tr, exited=True))
                continue
            if tr.reported and t - tr.report_t > RECHECK_S:
                out.append(st)
            elif tr.reported or (tr.frames >= p.min_track_frames and moved and (
                    tr.n_max >= p.min_features
                    or (self.lights_only and t - tr.first_t >= SMALL_S and abs(rep_y - tr.start_y) >= SMALL_M))):
                pending.append((tr, st, sign, members, length))
        # fragments are judged once every vehicle of this frame is up to date
        for tr, st, sign, members, length in pending:
            host = self._host_of(tr, st, sign, members, shadow, joined)
            if host is not None and self._was_cut_off(members, host):
                host = None
            if host == GHOST:  # the rest of a vehicle already finalised
                self._retire_as_part(tr, st, self._ghost_of, members, retire, out)
                continue
            if host is not None and tr.reported:
                off = self._place
                same = tr.votes[0] == host and abs(off - tr.votes[2]) <= RECHECK_DRIFT_M
                n = tr.votes[1] + 1 if same else 1
                tr.votes = (host, n, tr.votes[2] if same else off)
                tr.vote_t = t
                if n < RECHECK_VOTES:
                    out.append(replace(st, part_of=host))
                    continue
            elif not tr.reported and ((host in groups and self._k > LEVEL_K) or tr.watch_host):
                host = self._watched(tr, st, host if host in groups else None, groups)
                if host == WATCHING:
                    continue
                if host == GHOST:
                    self._retire_quietly(tr.id, members, retire)
                    continue
            if host is not None:
                self._absorb(members, host, groups[host], shade=self._by_shadow)
                self.tracks.pop(tr.id)
                self._end_as_part(tr, st, host, out)
                continue
            if not tr.reported:
                tr.reported = True
                tr.report_t = st.t
                # the earlier near-end points since settled_t, so that lines crossed before this report still count
                ahead = 0.0 if sign < 0 else tr.ground[1] - st.y_rear  # (as far ahead as the front reported)
                earlier = tr.trajectory[:-1]
                # a list, even with none of them left, marks the first report (the pipeline holds and extends it)
                st.trajectory = [(pt, px_, py + ahead) for pt, px_, py in earlier
                                 if pt >= self.settled_t] if earlier else None
                st.entered = self._entered(tr, st, ahead)
            elif self.matching_host(tr.id):  # no match this frame: no evidence either way
                st = replace(st, part_of=tr.votes[0])
            out.append(st)
        for vid in self._passed_through(t):
            self._retire_as_part(self.tracks[vid], _take_state(out, vid), NO_VEHICLE, groups[vid], retire, out)
        for part, host in [(a, b) for a, b in self._rigid_parts(t) if not self._was_cut_off(groups[a], b)]:
            st = _take_state(out, part)
            self._absorb(groups[part], host, groups[host])
            self._end_as_part(self.tracks.pop(part), st, host, out)
        med = None
        if small:
            members = np.concatenate([m for _, m in small])
            med = group_medians(members, np.cumsum([0] + [len(m) for _, m in small]), s, age)
        on_road = [a for a, (_, m) in enumerate(small) if not self.lifted[m].all()]  # tops take no late links
        road, road_med = [small[a] for a in on_road], med[on_road] if small else None
        self.late = self._late_slots(t, road, road_med, age)
        if is_joined is not None:
            for a, b in self._stacked(t, road, road_med, age, lambda a, b: is_joined(px[a], px[b])):
                self._link(a, b)
        adopted = [a for a in self._adopted(t, small, med, joined) if not self._was_cut_off(a[1], a[2])]
        for vid, members, host in adopted:
            self._absorb(members, host, groups[host], shade=True)  # high up: no part of its place on the road
            self.tracks.pop(vid)
        slots = np.concatenate(retire) if retire else np.zeros(0, np.int64)
        return [self._grounded(st, ground.get(st.id)) for st in out], slots

    def _late_slots(self, t: float, small: list[tuple[int, np.ndarray]], med: np.ndarray | None, age: np.ndarray
                    ) -> np.ndarray:
        """Per slot: whether it may link late (see LATE_BESIDE_M): a settled feature of a settled group of a
        lane that is too small to be reported (med: their group_medians), moves, and is alone, where its lane
        has another such group."""
        late = np.zeros(len(self.fvid), np.bool_)
        if not small:
            return late
        keep = np.abs(med[:, 2]) > MOVING_MPS
        lanes = np.array([self.tracks[vid].lane_index for vid, _ in small])
        ready = lanes[keep & (med[:, 3] >= SETTLED_AGE)]
        if len(ready) < 2 or len(np.unique(ready)) == len(ready):  # a late link needs two such groups in a lane
            return late
        small = [g for g, k in zip(small, keep) if k]
        sx, sy, sv, oldest = np.ascontiguousarray(med[keep].T)
        sl = lanes[keep]
        need = self.min_report
        big = np.array([(tr.lane_index, tr.last.x, min(tr.last.y_front, tr.last.y_rear), tr.last.vy, tr.x_lo, tr.x_hi,
                         max(tr.own_length, ELEVATED_LENGTH_M), tr.n_max >= need)
                        for tr in self.tracks.values() if tr.lane_index > 0 and tr.last is not None and tr.last.t == t],
                       np.float64).reshape(-1, 8)
        fx, fy = (self.foot[0], self.foot[1]) if self.foot is not None else (0.0, 0.0)
        alone = alone_groups(sl, sx, sy, sv, big, fx, fy, self.k_max if self.foot is not None else 1.0)
        for (_, m), ok in zip(small, alone & (oldest >= SETTLED_AGE)):
            if ok:
                late[m[age[m] >= SETTLED_AGE]] = True
        return late

    def _stacked(self, t: float, small: list[tuple[int, np.ndarray]], med: np.ndarray | None, age: np.ndarray,
                 joined: Callable[[np.ndarray, np.ndarray], bool]) -> list[tuple[np.ndarray, np.ndarray]]:
        """Pairs (further, nearer) of small groups' settled features that are parts of one tall vehicle (see
        STACK_S), seen so for STACK_HELD_S; joined(a, b): the image test of slots a and b being one body."""
        seen: dict[tuple[int, int], float] = {}
        out = []
        if self.foot is not None and len(small) >= 2:
            lanes = np.array([self.tracks[vid].lane_index for vid, _ in small])
            sign = self.zones.sign_by_index[lanes]
            q = med[:, 1] - self.foot[1]
            d, v = np.abs(q), np.abs(med[:, 2])
            ok = (v > MOVING_MPS) & (med[:, 3] >= SETTLED_AGE) & (med[:, 2] * sign > 0)
            v = np.where(ok, v, 1.0)
            ttf = d / v
            cars = np.array([(o.x, min(o.y_front, o.y_rear) - self.foot[1], o.vy)
                             for o in (tr.last for tr in self.tracks.values() if tr.reported)
                             if o is not None and o.t == t and abs(o.vy) > MOVING_MPS]).reshape(-1, 3)
            lag = ttf[:, None] - np.abs(cars[None, :, 1]) / np.abs(cars[None, :, 2])
            ok &= ~np.any((np.abs(med[:, 0:1] - cars[None, :, 0]) <= LATE_BESIDE_X_M)
                          & (q[:, None] * cars[None, :, 1] > 0) & (med[:, 2:3] * cars[None, :, 2] > 0)
                          & (lag >= -STACK_S) & (lag <= ELEVATED_LENGTH_M / np.abs(cars[None, :, 2]) + STACK_S), axis=1)
            r = np.maximum(v[:, None], v[None, :]) / np.minimum(v[:, None], v[None, :])
            faster_further = (d[:, None] >= d[None, :]) == (v[:, None] >= v[None, :])
            pair = (ok[:, None] & ok[None, :] & (lanes[:, None] == lanes[None, :]) & (q[:, None] * q[None, :] > 0)
                    & ((r <= LEVEL_K) | faster_further) & (r <= self.k_max)
                    & (np.abs(ttf[:, None] - ttf[None, :]) <= STACK_S)
                    & (np.abs(med[:, 0:1] - med[None, :, 0]) <= self.p.connection_lateral_m))
            for a, b in zip(*np.nonzero(np.triu(pair, 1))):
                if d[a] < d[b]:
                    a, b = b, a  # the further one joins the nearer one
                ma, mb = small[a][1], small[b][1]
                ma, mb = ma[age[ma] >= SETTLED_AGE], mb[age[mb] >= SETTLED_AGE]
                if not joined(ma, mb):
                    continue
                key = (min(small[a][0], small[b][0]), max(small[a][0], small[b][0]))
                seen[key] = self.stacked.get(key, t)
                if t - seen[key] >= STACK_HELD_S:
                    out.append((ma, mb))
        self.stacked = seen
        return out

    def _watched(self, tr: VehicleTrack, st: VehicleState, host: int | None, groups: dict[int, np.ndarray]
                 ) -> int | None:
        """A new group seen as an elevated part of host: a faster follower closing in on a vehicle looks just
        the same until either changes speed. It is watched WATCH_S (unreported) with its speed ratio to the
        host in every frame, matched there or not (its near end and the host's extent flicker); it then joins
        the host if it matched it in WATCH_MIN_HITS frames and the ratio held, else it is a vehicle (None).
        WATCHING meanwhile; GHOST if the host has gone (finished) with the group a part of it so far."""
        if host is not None and tr.watch_host != host:
            if tr.watch_host not in self.tracks and self._held(tr.watch):
                # the vehicle it was watched against has just left the view, matched all along: the group is
                # that vehicle's leftover (its next part in the view is no new evidence)
                tr.watch_host, tr.watch = 0, []
                return GHOST
            tr.watch_host, tr.watch = host, []  # another vehicle: start again
        other = self.tracks.get(tr.watch_host)
        if other is not None and other.last is not None and other.last.t == st.t:
            if other.last.vy * st.vy > 0:
                settled = not tr.unsure or st.t - tr.first_t >= WATCH_SETTLE_S
                tr.watch.append((st.t, st.vy / other.last.vy if settled else np.nan, settled and host is not None))
            if not tr.watch or st.t - tr.watch[0][0] < WATCH_S:
                return WATCHING
        watch, watched = tr.watch, tr.watch_host
        tr.watch_host, tr.watch = 0, []
        if not self._held(watch):
            return None
        if other is None or other.last is None or other.last.t != st.t:
            return GHOST
        return watched if watched in groups else None

    def _rigid_parts(self, t: float) -> list[tuple[int, int]]:
        """(part, host) pairs of reported groups of one lane where the part has moved as an elevated part of the
        host through a change of speed (see RIGID_S): checked every RIGID_EVERY frames of the part."""
        if self.foot is None:
            return []
        fy = self.foot[1]
        out: list[tuple[int, int]] = []
        taken: set[int] = set()
        for pid, part in self.tracks.items():
            if not part.reported or t - part.report_t <= RECHECK_S or part.frames % RIGID_EVERY or part.last is None \
                    or part.last.t != t or pid in taken:
                continue
            py = part.trajectory[-1][2]
            for hid, host in self.tracks.items():
                o = host.last
                if hid == pid or hid in taken or not host.reported or host.lane_index != part.lane_index \
                        or o is None or o.t != t or not 0.0 < py - host.trajectory[-1][2] <= ELEVATED_LENGTH_M:
                    continue
                if _moves_rigidly(part.trajectory, host.trajectory, fy):
                    out.append((pid, hid))
                    taken.update((pid, hid))
                    break
        return out

    def _adopted(self, t: float, small: list[tuple[int, np.ndarray]], med: np.ndarray | None,
                 joined: Callable[..., bool] | None) -> list[tuple[int, np.ndarray, int]]:
        """(group, members, vehicle) for the groups too small to be reported (med: their group_medians) that are
        high parts of a reported vehicle (see ADOPT_K_MIN); records each one's path and sets the vehicle's
        adopted place."""
        out: list[tuple[int, np.ndarray, int]] = []
        if not small or self.foot is None or joined is None:
            return out
        k_lo, k_hi = ADOPT_K_MIN * (1.0 - ADOPT_K_TOL), self.k_max * (1.0 + ADOPT_K_TOL)  # of the speed ratio
        due = []
        for (vid, members), row in zip(small, med):
            tr = self.tracks[vid]
            tr.path.append((t, row[0], row[1]))
            if tr.frames % ADOPT_EVERY == 0:
                tr.path = tr.path[bisect.bisect_left(tr.path, (t - ADOPT_S,)):]
                if len(tr.path) >= ADOPT_POINTS:
                    due.append((tr, members, row))
        hosts = [h for h in self.tracks.values() if h.reported and h.last is not None and h.last.t == t
                 and abs(h.last.vy) >= ADOPT_MIN_MPS] if due else []
        if not hosts:
            return out
        fy = self.foot[1]
        lane, hvy, d = np.array([(h.lane_index, h.last.vy, h.trajectory[-1][2] - fy) for h in hosts]).T
        part_lane = np.array([tr.lane_index for tr, _, _ in due])
        x, q, vy = np.array([row[:3] for _, _, row in due]).T
        q = q - fy
        r = vy[:, None] / hvy[None, :]  # [part, vehicle] speed ratio: k is within ADOPT_K_TOL of it (tested below)
        # beyond the vehicle's near end, and no further than the tallest vehicle's longest top projects
        qa, da = np.abs(q)[:, None], np.abs(d)[None, :]
        cand = ((np.abs(part_lane[:, None] - lane[None, :]) <= 1) & (r >= k_lo) & (r <= k_hi) & (q[:, None] * d > 0)
                & (da < qa) & (qa <= self.k_max * (da + ELEVATED_LENGTH_M + 1.0)))
        for a in np.flatnonzero(cand.any(axis=1)):
            tr, members, _ = due[a]
            k_min = self.k_top if self.lifted[members].all() else ADOPT_K_MIN
            ys = _by_time(tr.path, t - ADOPT_S)
            best = None
            for i in np.flatnonzero(cand[a]):
                h = hosts[i]
                pairs = _paired(ys, h.trajectory, t - ADOPT_S)
                if len(pairs) < ADOPT_POINTS or np.ptp(pairs[:, 1]) < ADOPT_TRAVEL_M:
                    continue
                k, c, res = _line_fit(pairs[:, 1], pairs[:, 2], fy)
                # its speed over the vehicle's now tells the same height (a near end held while the lowest
                # feature changes, or at the image's edge, makes a follower's fit look like a part's)
                if not k_min <= k <= self.k_max or abs(r[a, i] / k - 1.0) > ADOPT_K_TOL \
                        or res > ADOPT_RES_SHARE * abs(q[a]) or (best is not None and res >= best[0]):
                    continue
                place = c / k * np.sign(d[i])
                if place > ADOPT_FAR_M and k < self.k_far:
                    continue
                gx = self._on_road(x[a], fy + q[a], k)[0]
                x_lo, x_hi = h.elevated_x()
                if -1.0 <= place <= max(h.own_length, ELEVATED_LENGTH_M) + 1.0 \
                        and x_lo - FRAGMENT_X_MARGIN_M <= gx <= x_hi + FRAGMENT_X_MARGIN_M \
                        and joined(members, h.id, ADOPT_JOINED_SHARE):
                    best = (res, h, place)
            if best is not None:
                best[1].adopted = max(best[1].adopted, best[2])
                out.append((tr.id, members, best[1].id))
        return out

    @staticmethod
    def _held(watch: list[tuple[float, float, bool]]) -> bool:
        """Whether a watch (time, speed ratio, matched) matched its vehicle in WATCH_MIN_HITS frames with the
        ratio steady (see WATCH_K_DRIFT; the frames of a group watched on unsettled speeds, NaN, left out)."""
        if sum(hit for _, _, hit in watch) < WATCH_MIN_HITS:
            return False
        ks = np.array([k for _, k, _ in watch if np.isfinite(k)])
        m = max(len(ks) // 3, 1)  # the ratio over the first third of the watch and over the last
        return abs(np.median(ks[-m:]) / np.median(ks[:m]) - 1.0) <= WATCH_K_DRIFT

    def matching_host(self, vid: int) -> bool:
        """Whether a reported group is gathering votes to join a vehicle it may be a part of."""
        tr = self.tracks.get(vid)
        return tr is not None and tr.reported and 0 < tr.votes[1] < RECHECK_VOTES

    def _passed_through(self, t: float) -> list[int]:
        """Reported groups standing still for STALL_S that a moving vehicle of their lane drove through
        in this frame."""
        stuck = [tr for tr in self.tracks.values()
                 if tr.reported and tr.last is not None and tr.last.t == t and t - tr.still_t >= STALL_S]
        found = []
        for tr in stuck:
            for other in self.tracks.values():
                o = other.last
                if other is tr or other.lane_index != tr.lane_index or o is None or o.t != t:
                    continue
                if len(other.trajectory) < 2 or other.n_max < self.p.min_features or abs(o.vy) < MIN_SPEED_MPS:
                    continue
                y0, y1 = other.trajectory[-2][2], other.trajectory[-1][2]
                if (y0 - tr.still_y) * (y1 - tr.still_y) < 0 and abs(o.x - tr.last.x) <= PASS_X_M:
                    found.append(tr.id)
                    break
        return found

    def _ground_length(self, tr: VehicleTrack, sign: int, members: np.ndarray, s: np.ndarray, age: np.ndarray,
                       near_y: float, length: float) -> float:
        """The vehicle's length on the road: where its far fitted features (usually a roofline, projected
        beyond the vehicle by its height) lie over the road, plus the part of the vehicle hidden beyond it as a
        share of the length. Without a camera (SiteZones.length_camera): the features' span."""
        if self.length_foot is None or tr.lane_index <= 0:
            return length
        if sign > 0 and tr.fitted and tr.ground:
            # a receding vehicle is seen best as it enters, nearest the camera; its far end moves with it
            # from then on (a length that kept changing would add distance or time it did not travel)
            return max(tr.ground[0], tr.adopted)
        fy = self.length_foot[1]
        behind, k_end = fit_places(members, age, s, self.fit, self.fit_vid, tr.id, near_y - fy, fy,
                                   self.length_k_max, FIT_FRAMES, FIT_TRAVEL_SD_M ** 2, FIT_NEIGHBOUR_M)
        # until some are fitted, or while a feature not yet fitted lies further (a fragment that just joined):
        # the last length, or at first the features' span; never short of a part it adopted (a top's rear edge
        # is the vehicle's rear: nothing of it is hidden beyond)
        if np.isnan(behind):
            return max(tr.ground[0] if tr.ground else length, tr.adopted)
        tr.fitted = True
        if behind < FIT_MIN_EXTENT_M and not tr.adopted:
            return NOMINAL_LENGTH_M
        share = 0.0 if k_end <= self.length_k_level else HIDDEN_SHARE_FRONT if sign > 0 else HIDDEN_SHARE_REAR
        # never longer than the features' span now, whose far end is projected beyond the vehicle: a misfit
        # does not make a vehicle longer than what is seen of it
        g = max(min(behind / (1.0 - share), length), tr.adopted)
        if g < SHORTEST_CAR_M and tr.x_hi - tr.x_lo >= SINGLE_TRACK_MAX_WIDTH_M:
            return NOMINAL_LENGTH_M  # wider than a motorcycle, shorter than any car: only its front is seen
        return g

    def _split_off(self, tr: VehicleTrack, members: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, float] | None:
        """Cut a vehicle measured longer than LONGEST_M in two (see LONGEST_M): the mask of its members in front of
        the cut and how far behind its near end the cut lies, or None where it was not cut."""
        places, slopes = fitted_places(members, self.fit, self.fit_vid, tr.id, self.length_k_max, FIT_FRAMES,
                                       FIT_TRAVEL_SD_M ** 2)
        fitted = ~np.isnan(places)
        if np.count_nonzero(fitted) < 2 * self.min_report:
            return None
        places, slopes = places[fitted], slopes[fitted]
        order = np.argsort(places)
        p = places[order]
        if p[-1] <= LONGEST_M:
            return None
        gaps = np.diff(p)
        cut_at = np.arange(1, len(p))  # a cut before p[cut_at]
        ok = ((cut_at >= self.min_report) & (len(p) - cut_at >= self.min_report) & (gaps >= SPLIT_GAP_M)
              & (p[cut_at - 1] <= LONGEST_M))
        if not ok.any():
            return None
        c = cut_at[ok][np.argmax(gaps[ok])]
        if np.median(slopes[order[c:]]) < 1.0 - SPLIT_LAG:
            return None
        cut = 0.5 * (p[c - 1] + p[c])
        fs, others = members[fitted], members[~fitted]
        behind = np.zeros(len(members), np.bool_)
        behind[fitted] = places > cut
        if len(others):  # each goes with the fitted feature nearest it (as projected on the road)
            d = np.abs(s[others, 1][:, None] - s[fs, 1][None, :]) + np.abs(s[others, 0][:, None] - s[fs, 0][None, :])
            behind[~fitted] = (places > cut)[np.argmin(d, axis=1)]
        behind &= ~(self.shade[members] | self.lifted[members])
        rear, front = members[behind], members[~behind]
        self.state[np.minimum.outer(rear, front), np.maximum.outer(rear, front)] = APART
        self.fvid[rear] = -1
        self.cut_off[rear] = tr.id
        tr.adopted = min(tr.adopted, cut)
        return ~behind, cut

    def _was_cut_off(self, members: np.ndarray, host: int | None) -> bool:
        """Whether a group holds features cut off vehicle host (see LONGEST_M)."""
        return host is not None and host >= 0 and bool(np.any(self.cut_off[members] == host))

    @staticmethod
    def _grounded(st: VehicleState, ground: tuple[float, float, int] | None) -> VehicleState:
        """The reported copy of a state: its far end and length on the road (the tracker keeps the
        features' span for judging fragments)."""
        if ground is None:
            return st
        g, far, sign = ground
        if sign > 0:  # receding: the far end is the front (a one-feature group's span gives no direction)
            return replace(st, y_front=far, length=g)
        return replace(st, y_rear=far, length=g)

    def _host_of(self, tr: VehicleTrack, st: VehicleState, sign: int, members: np.ndarray,  # noqa: C901
                 shadow: Callable[[np.ndarray, int], bool] | None,
                 joined: Callable[[np.ndarray, int], bool] | None) -> int | None:
        """A reported vehicle that this group (new, or reported less than RECHECK_S ago) is a part of: after
        undoing the height magnification (its projected speed over the vehicle's, k >= 1) the group's near end
        falls inside the vehicle's footprint, or (an elevated part with the image between them one body) a
        footprint as long and wide as any vehicle's: see ELEVATED_LENGTH_M. Tall vehicles' tops seen in the next
        lane, or behind them, are such fragments. GHOST for the rest of a vehicle finalised in the last GHOST_S
        (self._ghost_of says which). Sets self._place (where on the host the group lies) for the caller's
        steadiness votes."""
        y = tr.trajectory[-1][2]
        # a reported group's speed over a while (steadier); a new one has only its features' speeds
        vy = st.vy
        if tr.reported:
            vy = tr.steady_vy(st.vy)
        self._ghost_of = self._leftover_of(tr, st, y, vy)
        if self._ghost_of is not None:
            return GHOST
        self._k = 1.0
        self._by_shadow = False
        side = self._side_host(tr, st, y, vy, members, sign, shadow, joined)
        if side is not None:
            return side
        # where the group's near end may lie on the road once a height magnification is undone (a cheap test
        # that spares most vehicles the rest)
        g_lo = g_hi = y
        if self.foot is not None:
            g_far = self._on_road(st.x, y, self.k_max)[1]
            g_lo, g_hi = min(y, g_far), max(y, g_far)
        for vid, other in self.tracks.items():
            o = other.last
            if vid == tr.id or o is None or o.t != st.t or o.vy * vy <= 0:
                continue
            if not other.reported and (other.first_t > tr.first_t or other.n_max < tr.n_max):
                continue
            if not tr.reported and other.n_now < tr.n_now:
                continue  # a new group is a part of a larger one, not the other way round
            if tr.reported and (not other.reported or other.report_t > tr.report_t):
                continue  # a reported vehicle only joins one reported before it
            lo, hi = _extent(o, other.own_length)
            if g_hi < lo or g_lo > _elevated_reach(lo, hi):
                continue
            ov = other.steady_vy(o.vy) if tr.reported else o.vy
            if ov * vy <= 0:
                continue
            k = vy / ov
            if not (RECHECK_K_MIN if tr.reported else 0.85) <= k <= self.k_max:
                continue
            gx, gy = st.x, y
            m = FRAGMENT_X_MARGIN_M
            if k > LEVEL_K:
                if self.foot is not None:
                    gx, gy = self._on_road(st.x, y, k)
                else:  # camera unknown: an elevated part may lie anywhere across the vehicle's lane
                    m = FRAGMENT_X_MARGIN_NO_CAMERA_M
            on = lo <= gy <= hi and other.x_lo - m <= gx <= other.x_hi + m
            # a part seen in the next lane may be a follower there: in slow traffic (see ADOPT_MIN_MPS), and at any
            # speed beside a vehicle too short to be tall (SIDE_TALL_HOST_M)
            ask_image = on and k > LEVEL_K and other.lane_index != tr.lane_index and (
                abs(ov) < ADOPT_MIN_MPS or other.own_length < SIDE_TALL_HOST_M)
            if not on and k > LEVEL_K and self.foot is not None:
                on = ask_image = other.carries(gx, gy, m)
            if ask_image:  # the image test last: it is the dearest
                on = joined is not None and joined(members, vid)
            if on:
                self._place = gy - o.y_front  # where on the vehicle the group lies
                self._k = k
                return vid
        if not tr.reported and not tr.watch_host:
            return self._unsure_host(tr, st, y, vy, members, joined)
        return None

    def _unsure_host(self, tr: VehicleTrack, st: VehicleState, y: float, vy: float, members: np.ndarray,
                     joined: Callable[[np.ndarray, int], bool] | None) -> int | None:
        """A vehicle that a new group, first judged, could be an elevated part of at some height (its
        features' speeds, a frame or two old, do not tell it yet: see UNSURE_K): the group is then watched
        against it (see _watched), which judges it on its speeds as they settle."""
        if self.foot is None or joined is None:
            return None
        fy = self.foot[1]
        for vid, other in self.tracks.items():
            o = other.last
            if vid == tr.id or not other.reported or o is None or o.t != st.t or o.vy * vy <= 0:
                continue
            if other.n_now < tr.n_now or not UNSURE_K[0] <= vy / o.vy <= UNSURE_K[1] or abs(o.vy) < PART_MIN_MPS:
                continue
            if other.lane_index != tr.lane_index and other.own_length < SIDE_TALL_HOST_M:
                continue  # only a tall vehicle's top is seen over the next lane
            lo, hi = _extent(o, other.own_length)
            hi = _elevated_reach(lo, hi)
            # the heights (k from LEVEL_K to k_max) that put the near end on the vehicle, along and across
            k_along = ((y - fy) / (hi - fy) if hi > fy else np.inf, (y - fy) / (lo - fy) if lo > fy else np.inf)
            x_lo, x_hi = other.elevated_x()
            x_lo, x_hi = x_lo - FRAGMENT_X_MARGIN_M, x_hi + FRAGMENT_X_MARGIN_M
            k_lo, k_hi = max(LEVEL_K + 0.01, k_along[0]), min(self.k_max, k_along[1])  # elevated: watched
            if k_lo > k_hi:
                continue
            k = np.linspace(k_lo, k_hi, 8)
            gx = self._on_road(st.x, y, k)[0]
            fits = (gx >= x_lo) & (gx <= x_hi)
            if not fits.any() or not joined(members, vid):
                continue
            self._k = float(k[np.argmax(fits)])
            self._place = self._on_road(st.x, y, self._k)[1] - o.y_front
            tr.unsure = True
            return vid
        return None

    def _side_host(self, tr: VehicleTrack, st: VehicleState, y: float, vy: float, members: np.ndarray,
                   sign: int, shadow: Callable[[np.ndarray, int], bool] | None,
                   joined: Callable[[np.ndarray, int], bool] | None = None) -> int | None:
        """A vehicle in a neighbouring lane of the same direction whose side part this group is: same
        speed, near ends level, and either a receding vehicle's flank (joint footprint no wider than one
        vehicle, or than a tall one's projection where the image between them is its body; on the camera's side
        of the vehicle its near end at most SIDE_NEAR_MAX_WIDTH_M wide) or only a shadow on the road (the image
        says so; a low sun casts one across the next lane into the lane beyond, see SHADOW_LANES). A reported
        group is compared by its speed over a while, and with a vehicle reported after it only as its shadow or a
        much smaller flank (a receding vehicle's shadow cast ahead of it enters the view first); sets self._place
        for the votes."""
        for vid, other in self.tracks.items():
            o = other.last
            if vid == tr.id or o is None or o.t != st.t or other.lane_index == tr.lane_index:
                continue
            lanes_apart = abs(other.lane_index - tr.lane_index)
            if lanes_apart > SHADOW_LANES or o.vy * vy <= 0:
                continue
            if not other.reported and (other.first_t > tr.first_t or other.n_max < self.p.min_features):
                continue
            if tr.reported and not other.reported:
                continue
            place = y - other.trajectory[-1][2]
            dy = abs(place)
            if dy > SHADOW_DY_M:
                continue
            # a part reported before its vehicle: its shadow, or its flank if the vehicle is much the bigger
            late = tr.reported and other.report_t > tr.report_t
            flank = not late or other.n_now >= SIDE_LATE_HOST_K * tr.n_now
            ov = other.steady_vy(o.vy) if tr.reported else o.vy
            if ov * vy <= 0:
                continue
            self._place = place
            dv = abs(vy / ov - 1.0)
            if dv > SHADOW_SPEED_TOL:
                continue
            gap = max(tr.x_lo - other.x_hi, other.x_lo - tr.x_hi)
            width = max(tr.x_hi, other.x_hi) - min(tr.x_lo, other.x_lo)
            lo, hi = _extent(o, other.own_length)
            if lanes_apart > 1:
                pass  # only its shadow reaches across a lane (below)
            elif flank and sign > 0 and gap <= SIDE_GAP_M and width <= SIDE_MAX_WIDTH_M and (
                    not self._on_cameras_side(st.x, other) or tr.x_hi - tr.x_lo <= SIDE_NEAR_MAX_WIDTH_M):
                if dy <= SIDE_DY_M and dv <= SIDE_SPEED_TOL:
                    return vid
                # a reported part is watched longer (the votes): anywhere along the vehicle, speeds less sure
                if tr.reported and lo <= y <= hi and dv <= SIDE_SPEED_TOL_WATCHED:
                    return vid
            elif (flank and sign > 0 and gap <= SIDE_GAP_M and width <= SIDE_MAX_WIDTH_TALL_M and dy <= SIDE_DY_M
                  and dv <= SIDE_SPEED_TOL and hi - lo >= SIDE_TALL_HOST_M and self._leans_away(st.x, o.x)
                  and (width <= SIDE_PAIR_WIDTH_M or tr.n_now < other.n_now)
                  and joined is not None and joined(members, vid)):
                return vid  # a tall vehicle's flank or top, wider in projection: the image between is its body
            tip = tr.n_now < self.p.min_features
            if (gap <= (TIP_GAP_M if tip else SHADOW_GAP_M)
                    and width <= (TIP_MAX_WIDTH_M if tip else SHADOW_MAX_WIDTH_M)
                    and shadow is not None and shadow(members, vid)):
                self._by_shadow = True
                return vid
        return None

    def _leftover_of(self, tr: VehicleTrack, st: VehicleState, y: float, vy: float) -> int | None:
        """The vehicle finalised in the last GHOST_S whose leftover group tr is, its near end at y moving at vy; None
        if none. A new group lying in its extent (moved on at its speed) at 0.85-2.5 times its speed; or, the
        camera known, the top of one of its lane that left the view (see GHOST_S), a reported group at
        RECHECK_K_MIN times its speed at least, as it must to join a vehicle still in view."""
        k_min = RECHECK_K_MIN if tr.reported else LEVEL_K
        for o, x_lo, x_hi, lane in self.recent:
            if o.vy * vy <= 0:
                continue
            k = vy / o.vy
            dy = o.vy * (st.t - o.t)
            lo, hi = _extent(o)
            lo, hi = lo + dy, hi + dy
            # an elevated leftover (moving faster in projection) may lie across the lane; a level one may not
            m = FRAGMENT_X_MARGIN_NO_CAMERA_M if k > LEVEL_K else FRAGMENT_X_MARGIN_M
            if not tr.reported and 0.85 <= k <= 2.5 and lo <= y <= hi and x_lo - m <= st.x <= x_hi + m:
                return o.id
            if (self.foot is not None and o.exited and lane == tr.lane_index and abs(o.vy) >= ADOPT_MIN_MPS
                    and k_min < k <= self.k_max):
                gx, gy = self._on_road(st.x, y, k)  # (its far end is projected: a top's reach is from its near end)
                if _elevated_on(gx, gy, lo, lo, x_lo, x_hi, FRAGMENT_X_MARGIN_M):
                    return o.id
        return None

    def _raised_over(self, slots: np.ndarray, host: int, s: np.ndarray) -> bool:
        """Whether features are raised parts of vehicle host: each faster than it in projection as a part above
        the road is (LEVEL_K to k_max), and their height magnification undone, their middle over its footprint."""
        o = self.tracks[host].last
        if self.foot is None or o is None or abs(o.vy) < MOVING_MPS:
            return False
        k = s[slots, 3] / o.vy
        if not ((k > LEVEL_K) & (k <= self.k_max)).all():
            return False
        gx, gy = self._on_road(s[slots, 0], s[slots, 1], k)
        return self.tracks[host].carries(float(np.median(gx)), float(np.median(gy)))

    def _on_road(self, x: float | np.ndarray, y: float | np.ndarray, k: float | np.ndarray
                 ) -> tuple[float | np.ndarray, float | np.ndarray]:
        """Where on the road lies what is seen at road-plane point(s) (x, y) with height magnification k (the
        camera's foot must be known)."""
        fx, fy = self.foot[0], self.foot[1]
        return fx + (x - fx) / k, fy + (y - fy) / k

    def _leans_away(self, x: float, host_x: float) -> bool:
        """Whether a point at x across the road lies on the side of a vehicle at host_x away from the camera,
        where its raised parts are projected."""
        return self.foot is not None and (x - host_x) * (host_x - self.foot[0]) > 0.0

    def _on_cameras_side(self, x: float, host: VehicleTrack) -> bool:
        """Whether a point at x across the road lies on the camera's side of vehicle host, where none of its raised
        parts are projected: the camera known, its foot not within the host's near end across the road (raised
        parts lean both ways from there), and x not leaning away from the host."""
        return (self.foot is not None and not host.x_lo <= self.foot[0] <= host.x_hi
                and not self._leans_away(x, host.last.x))

    def _lose(self, tr: VehicleTrack, t: float, out: list[VehicleState]) -> None:
        """A vehicle's features are gone: it is finished if it had left its detection zone, else remembered
        where it was lost (it may be found again as a new group)."""
        if self._orphaned_part(tr, t):
            self._end_as_part(tr, tr.last, tr.votes[0], out)
        elif self._qualifies_on_loss(tr):
            out.append(self._finish(tr, exited=False))
        elif tr.reported and tr.trajectory:  # a reported vehicle has a last state
            last = tr.last
            self.lost.append(Lost(t, tr.lane_index, tr.trajectory[-1][2], abs(last.vy), last.x, last.y_front,
                                  t - tr.report_t < LOST_MIN_REPORTED_S))

    def _absorb(self, members: np.ndarray, host: int, host_members: np.ndarray, shade: bool | None = None) -> None:
        """A part's features become vehicle host's for good (linked to its features; with shade, marked as a
        shadow of it or not)."""
        self._link(members, host_members)
        self.fvid[members] = host
        if shade is not None:
            self.shade[members] = shade
        self.tracks[host].merged = True

    def _end_as_part(self, tr: VehicleTrack, st: VehicleState | None, host: int, out: list[VehicleState]) -> None:
        """Group tr ends as a part of vehicle host (or of none: NO_VEHICLE): never a vehicle of its own (the
        pipeline drops its held report, see merged_now); a reported one's last state tells the measures whom it
        joined (VehicleState.joined)."""
        self.merged_now.add(tr.id)
        if tr.reported and st is not None:
            out.append(replace(st, finished=True, joined=host))

    def _orphaned_part(self, tr: VehicleTrack, t: float) -> bool:
        """Whether a young reported group ending now (exited or lost) is a part of another vehicle: its report
        still on recheck, it was gathering votes to join that vehicle (ORPHAN_VOTES of them at least, at one place
        on it) when one of the two left the view (its last vote within ORPHAN_GAP_S, or that vehicle gone since).
        Its report is then never released."""
        return (tr.reported and t - tr.report_t <= RECHECK_S and tr.votes[1] >= ORPHAN_VOTES
                and (t - tr.vote_t <= ORPHAN_GAP_S or tr.votes[0] not in self.tracks))

    def _retire_as_part(self, tr: VehicleTrack, st: VehicleState | None, host: int, members: np.ndarray,
                        retire: list[np.ndarray], out: list[VehicleState]) -> None:
        """End group tr as a part of vehicle host (or of none: NO_VEHICLE), as _end_as_part does, and retire its
        features: host has gone, or there is none, to take them."""
        self._end_as_part(tr, st, host, out)
        self._retire_quietly(tr.id, members, retire)

    def _retire_quietly(self, vid: int, members: np.ndarray, retire: list[np.ndarray]) -> None:
        """End a group that is no vehicle of its own: its track dropped, its held report never released (the
        pipeline drops what is in merged_now), its features retired. A last state, if any, is the caller's."""
        self.tracks.pop(vid)
        self.merged_now.add(vid)
        retire.append(members)

    @staticmethod
    def _lone_shadow(tr: VehicleTrack, t: float, pts: np.ndarray,
                     is_shadow: Callable[[np.ndarray, np.ndarray | None], bool]) -> bool:
        """Whether a young group (until RECHECK_S after its report) has turned out to be only a shadow."""
        if tr.reported and t - tr.report_t > RECHECK_S:
            return False
        t0, n, hits = tr.shadow_tests or (t, 0, 0)
        n, hits = n + 1, hits + int(is_shadow(pts, None))
        tr.shadow_tests = (t0, n, hits)
        return t - t0 >= LONE_SHADOW_S and n >= LONE_SHADOW_TESTS and hits >= LONE_SHADOW_SHARE * n

    def _entered(self, tr: VehicleTrack, st: VehicleState, ahead: float) -> bool:
        """Whether a newly reported vehicle entered the view: its trajectory begins in its lane's detection zone
        (or its near end lay there while it was begun afresh at the image's bottom: see ENTER_ROWS_K), and
        not where a reported vehicle of its lane lost in the last LOST_KEEP_S could be by then at the speed it has
        (found again, it must not count again: see LOST_ACCEL_MPS2; one lost soon after its report only past its
        count line, see LOST_MIN_REPORTED_S). Found again past its count line where it was lost short of it, it
        starts from where it was lost (st.trajectory, whose points are its front ``ahead`` of its near end), so
        that it counts there once: a vehicle whose features were all lost in its detection zone (hidden by one in
        the next lane, or standing in a queue) and found again only past its count line was never counted."""
        if tr.lane_index <= 0:
            return False
        lz = self.zones.by_index(tr.lane_index)
        y0 = tr.trajectory[0][2]
        self.lost = [lo for lo in self.lost if st.t - lo.t <= LOST_KEEP_S]
        t0 = tr.trajectory[0][0]
        past = lz.sign * (y0 + ahead - lz.count_y) >= 0
        found = [lo for lo in self.lost if lo.lane_index == tr.lane_index and (past or not lo.brief)
                 and _reachable(lz.sign * (y0 - lo.near), lo.speed, max(t0 - lo.t, 0.0))
                 and _could_reach_speed(abs(st.vy), lo.speed, lz.sign * (tr.trajectory[-1][2] - lo.near))]
        short = [lo for lo in found if lo.t < t0 and lz.sign * (lo.front - lz.count_y) < 0]
        if short and past:
            lo = max(short, key=lambda lo: lo.t)
            self.lost.remove(lo)
            st.trajectory = [(lo.t, lo.x, lo.front)] + (st.trajectory or [])
        return (lz.in_detection(y0) or tr.entered_at_bottom) and not found

    def _link(self, a: np.ndarray, b: np.ndarray) -> None:
        """Join features a to the vehicle of features b for good."""
        self.state[np.minimum.outer(a, b), np.maximum.outer(a, b)] = np.where(  # pairs kept as (lower, higher)
            np.less.outer(a, b), MERGED_LO, MERGED_HI)

    def _qualifies_on_loss(self, tr: VehicleTrack) -> bool:
        """A vehicle whose features were all lost still counts if it left the detection zone."""
        if not tr.reported or tr.last is None or tr.lane_index <= 0:
            return False
        lz = self.zones.by_index(tr.lane_index)
        y = tr.trajectory[-1][2]
        d0, d1 = lz.detection_y
        return y < d0 if lz.sign < 0 else y > d1

    def _finish(self, tr: VehicleTrack, exited: bool) -> VehicleState:
        st = tr.last
        self.finished_total += 1
        self.recent.append((replace(st, exited=exited), tr.x_lo, tr.x_hi, tr.lane_index))
        return self._grounded(replace(st, finished=True, exited=exited, trajectory=None), tr.ground)


def _paired(part: dict[float, float], host: list[tuple[float, float, float]], t0: float) -> np.ndarray:
    """(t, host's Y, part's Y) at the times from t0 that both were seen (every point of one frame carries that
    frame's time); part: its Y by time (see _by_time)."""
    return np.array([(p[0], p[2], part[p[0]]) for p in host[bisect.bisect_left(host, (t0,)):]
                     if p[0] in part]).reshape(-1, 3)


def _by_time(points: list[tuple[float, float, float]], t0: float) -> dict[float, float]:
    """Y by time of the points from t0."""
    return {p[0]: p[2] for p in points[bisect.bisect_left(points, (t0,)):]}


def _line_fit(ya: np.ndarray, yb: np.ndarray, fy: float) -> tuple[float, float, float]:
    """(k, c, RMS residual) of the least-squares line yb - fy = k (ya - fy) + c (ya not all equal)."""
    a, b = ya - fy, yb - fy
    da, db = a - a.mean(), b - b.mean()
    k = float(np.dot(da, db) / np.dot(da, da))
    r = db - k * da
    return k, float(b.mean() - k * a.mean()), float(np.sqrt(np.dot(r, r) / len(r)))


def _moves_rigidly(part: list[tuple[float, float, float]], host: list[tuple[float, float, float]], fy: float) -> bool:
    """Whether over their last RIGID_S together the part's near end lay at k times the host's distance from the
    camera's foot plus a constant (an elevated part of it: RIGID_K), within RIGID_RES_M, while the host's speed
    changed by RIGID_DV_MPS or more."""
    t0 = min(part[-1][0], host[-1][0]) - RIGID_S
    pairs = _paired(_by_time(part, t0), host, t0)
    if len(pairs) < 10 or pairs[-1, 0] - pairs[0, 0] < 0.9 * RIGID_S:
        return False
    tt, ya, yb = pairs.T
    v = np.abs(np.diff(ya) / np.maximum(np.diff(tt), 1e-3))
    n = max(len(v) // 8, 1)
    vs = np.convolve(v, np.ones(n) / n, mode="valid")
    if vs.max() - vs.min() < RIGID_DV_MPS:
        return False
    k, _, res = _line_fit(ya, yb, fy)
    return RIGID_K[0] <= k <= RIGID_K[1] and res <= RIGID_RES_M


def _reachable(ahead: float, speed: float, dt: float) -> bool:
    """Whether a vehicle lost dt seconds ago at this speed (m/s) can be ``ahead`` metres on from where it was
    lost (within REFOUND_M): between where the hardest braking and holding its speed take it."""
    stop_t = speed / LOST_BRAKE_MPS2
    least = speed * dt - 0.5 * LOST_BRAKE_MPS2 * dt * dt if dt < stop_t else 0.5 * speed * stop_t
    return least - REFOUND_M <= ahead <= speed * dt + REFOUND_M


def _could_reach_speed(speed: float, lost_speed: float, travel: float) -> bool:
    """Whether a vehicle lost at lost_speed (m/s) can move at ``speed`` once ``travel`` metres on from where it
    was lost (see LOST_ACCEL_MPS2)."""
    top = math.sqrt(lost_speed * lost_speed + 2.0 * LOST_ACCEL_MPS2 * max(travel + REFOUND_M, 0.0))
    return speed <= top + LOST_SPEED_SLACK_MPS


def _near_end_stopped_dead(tr: VehicleTrack, t: float) -> bool:
    """Whether a vehicle's near end came to stand (for STILL_S, in the last STALL_S) from DEAD_NEAR_MPS or
    more over the DEAD_STOP_S before (the median of its steps: one jump, as a lower feature appears, is no
    speed): no vehicle stops that hard."""
    if not STILL_S <= t - tr.still_t <= STALL_S:
        return False
    before = []  # its points over the DEAD_STOP_S up to the stand, latest first
    for p in reversed(tr.trajectory):
        if p[0] < tr.still_t - DEAD_STOP_S - 1e-9:
            break
        if p[0] <= tr.still_t:
            before.append(p)
    if len(before) < 4 or before[0][0] != tr.still_t:
        return False
    tt = np.array([p[0] for p in before[::-1]])
    yy = np.array([p[2] for p in before[::-1]])
    return float(np.median(np.abs(np.diff(yy)) / np.maximum(np.diff(tt), 1e-6))) >= DEAD_NEAR_MPS
