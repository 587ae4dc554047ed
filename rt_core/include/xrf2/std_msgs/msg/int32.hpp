// std_msgs::msg::Int32 as a plain struct: XRF2's command bridge header included ROS 2's
// <std_msgs/msg/int32.hpp> (the XenoCmd / XenoState message), so student code could use the type,
// and the standard headers rosidl's message headers include (<memory>, <vector>, ...) were
// visible through it. The loop process links no ROS library (the bridge runs in its own process),
// so the type is provided here the way the project's own messages are (msgdef.py): same name,
// same field, the member aliases rosidl generates.
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>
#include <memory>
#include <sstream>
#include <string>
#include <type_traits>
#include <vector>

namespace std_msgs
{
namespace msg
{

struct Int32 {
    using _data_type = int32_t;
    int32_t data = 0;

    Int32 &set__data(const int32_t &value)
    {
        data = value;
        return *this;
    }

    using SharedPtr = std::shared_ptr<Int32>;
    using ConstSharedPtr = std::shared_ptr<const Int32>;
    using UniquePtr = std::unique_ptr<Int32>;
    using ConstUniquePtr = std::unique_ptr<const Int32>;
    using Ptr = SharedPtr;
    using ConstPtr = ConstSharedPtr;

    bool operator==(const Int32 &other) const { return data == other.data; }
    bool operator!=(const Int32 &other) const { return !(*this == other); }
};

} // namespace msg
} // namespace std_msgs
