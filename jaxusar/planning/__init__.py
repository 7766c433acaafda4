"""Planning: the ground truth that defines "optimal" (PAPER.md), and the references teams are measured against.

"Optimal" on a map with fixed victims is the fewest joint primitive steps (TRIAGE and clearing actions
count) for the whole team to triage every victim from the reset state: ``optimal_team_steps``, by an exact
breadth-first search over the joint state of every agent (``search.py``; the successors are the env's own
``step``), so agents blocking each other, rubble the engineers must clear first and victims needing several
TRIAGE actions are exact. Where critical victims expire, "optimal" is the highest undiscounted episode
return instead (rewards of the victims triaged + step_penalty x steps; an episode ends when every victim is
triaged or dead, or at the horizon), and among equal returns the fewest steps: ``optimal_team_return``
(the search's layers are time, so a state's dead victims follow from its triaged flags and its depth).
Where victims are drawn at reset, no single plan is optimal for every draw: ``clairvoyant_reference`` is
the mean over a fixed sample of draws of the best return knowing the draw, exact or a bound no policy can
beat.

``optimal_team_plan(env)``: one shortest joint action sequence (the same search, recording parents).
``agent_distances(env, agent)``: the per-agent shortest distances (the agent alone on the map, victims as
obstacles) to enter each region and to triage each victim; the sub-policies' optimum (with
``steps_to_goal``, ``distances.py``).
``team_lower_bound(env)``, ``episode_lower_bound``, ``team_return_bound``: bounds that stay cheap at any map
size (``bounds.py``). ``team_reference(env)``: what training measures teams against on every map
(``reference.py``).
"""

from jaxusar.planning.bounds import StateBounds, episode_lower_bound, team_lower_bound, team_return_bound
from jaxusar.planning.distances import (
    _fixed_point, _pose_index, _single_agent_successors, pose_distances, steps_to_clear, steps_to_goal,
)
from jaxusar.planning.optimal import optimal_team_plan, optimal_team_return, optimal_team_steps, return_search_exact
from jaxusar.planning.reference import (
    CLAIRVOYANT_MAX_STATES, PRUNED_SEARCH_MAX_BOUND, SEARCH_MAX_BOUND, clairvoyant_reference, fixed_victims, in_reach,
    team_reference,
)
from jaxusar.planning.search import (
    SearchTooLarge, Unreachable, _all_triaged, _bfs, _check_size, _search, agent_distances, joint_states_bound,
)

__all__ = [
    "optimal_team_steps", "optimal_team_plan", "optimal_team_return", "agent_distances", "steps_to_goal", "steps_to_clear",
    "pose_distances", "team_lower_bound", "episode_lower_bound", "team_return_bound", "StateBounds",
    "team_reference", "clairvoyant_reference", "fixed_victims", "in_reach", "return_search_exact", "joint_states_bound",
    "SEARCH_MAX_BOUND", "PRUNED_SEARCH_MAX_BOUND", "CLAIRVOYANT_MAX_STATES", "Unreachable", "SearchTooLarge",
]
