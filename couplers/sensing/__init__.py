"""The sensor models: what each vehicle and road-side unit measures of the true states."""
