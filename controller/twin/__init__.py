"""The rig's twin (pure): a simulated rig built from the plant knowledge (`model.RigTwin`,
`fit.twin_from_knowledge`)."""
