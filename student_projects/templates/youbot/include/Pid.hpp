#ifndef PID_HPP
#define PID_HPP

// A discrete PID with output clamping and anti-windup by conditional integration, sized for
// one call per loop cycle. Header-only: nothing here allocates or blocks.
class Pid
{
public:
    Pid(double kp, double ki, double kd, double output_limit, double cycle_time)
        : kp_(kp), ki_(ki), kd_(kd), limit_(output_limit), dt_(cycle_time)
    {
    }

    void reset(double error = 0.0)
    {
        integral_ = 0.0;
        last_error_ = error;
    }

    double update(double error)
    {
        double derivative = (error - last_error_) / dt_;
        last_error_ = error;
        double candidate = integral_ + error * dt_;
        double raw = kp_ * error + ki_ * candidate + kd_ * derivative;
        double out = raw > limit_ ? limit_ : (raw < -limit_ ? -limit_ : raw);
        // Integrate only while the output is not saturated, or when the error pulls it back.
        if (out == raw || (error > 0.0) != (raw > 0.0))
            integral_ = candidate;
        return out;
    }

private:
    double kp_, ki_, kd_, limit_, dt_;
    double integral_ = 0.0;
    double last_error_ = 0.0;
};

#endif // PID_HPP
