"""The names of the interface features (docs/ARCHITECTURE.md, "Interface features").

The one definition of the contract between the systems that compute the features
(:meth:`filters.submap.SubmapSLAM.interface_features`), the env that shows them (its observation
vector, in this order, and ``info["features"]``) and the policies that read them. This module
imports nothing.
"""

INTERFACE_FEATURE_NAMES: tuple[str, ...] = (
    "local_map_age_s",
    "local_map_distance_m",
    "ess_ratio",
    "particle_position_spread_m",
    "particle_heading_spread_rad",
    "local_feature_count",
    "local_confirmed_count",
    "vote_margin",
    "innovation_ratio",
    "global_features_in_view",
    "global_position_std_m",
    "global_heading_std_rad",
    "time_since_optimise_s",
    "fusions_since_optimise",
    "clutter_rate",
    "loop_closure_flag",
    "local_map_budget_ratio",
    "loop_closures_since_optimise",
    "stored_submaps",
)
"""The interface features, in table order (the env's observation order)."""
