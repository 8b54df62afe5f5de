"""Looking inside recurrent agents: state traces, response types, interventions, unintentional triggers, search."""
