from stepnft.policies.flow.configuration_flow import FlowPolicyConfig
from stepnft.policies.flow.modeling_flow import FlowPolicy

__all__ = ["FlowPolicy", "FlowPolicyConfig"]
